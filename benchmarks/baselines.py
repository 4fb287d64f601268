"""numpy/scipy baselines the benchmark measures jaxtable against, written as a user would
write them: the compensated command in vectorised numpy ((N, 6, 3) arrays, the twist from the
cross products m = n×u, k = j×u as in the paper), and forward kinematics with
`scipy.optimize.fsolve` pose by pose on that numpy model. They live outside the package so the
installed library carries one kinematics only; the tests check them against jaxtable."""

import numpy as np

from jaxtable import Table


def numpy_rotation(angles: np.ndarray) -> np.ndarray:
    """(N, 3) roll, pitch, yaw -> (N, 3, 3), R = Rz Ry Rx."""
    f, t, p = angles[:, 0], angles[:, 1], angles[:, 2]
    cf, sf, ct, st, cp, sp = np.cos(f), np.sin(f), np.cos(t), np.sin(t), np.cos(p), np.sin(p)
    R = np.empty((len(angles), 3, 3))
    R[:, 0] = np.stack([cp * ct, cp * st * sf - sp * cf, cp * st * cf + sp * sf], -1)
    R[:, 1] = np.stack([sp * ct, sp * st * sf + cp * cf, sp * st * cf - cp * sf], -1)
    R[:, 2] = np.stack([-st, ct * sf, ct * cf], -1)
    return R


def numpy_command(table: Table, poses: np.ndarray) -> np.ndarray:
    """Baseline: compensated command |l_i| − lead·Δα_i/(2π), (N, 6) mm, vectorised numpy."""
    a = np.asarray(table.platform_joints)
    b = np.asarray(table.base_joints)
    n_ax = np.asarray(table.base_axes)
    jp = np.asarray(table.platform_axes)
    lead = np.asarray(table.signed_lead)

    def twist(q):
        R = numpy_rotation(q[:, 3:])
        t = q[:, :3] + np.array([0.0, 0.0, float(table.home_height)])
        l = t[:, None, :] + np.einsum("nij,kj->nki", R, a) - b
        L = np.linalg.norm(l, axis=-1)
        u = l / L[..., None]
        j = np.einsum("nij,kj->nki", R, jp)
        m = np.cross(n_ax, u)
        k = np.cross(j, u)
        return L, np.sum(u * np.cross(m, k), -1), np.sum(m * k, -1)

    L, s, c = twist(poses)
    _, s0, c0 = twist(np.zeros((1, 6)))
    beta = np.arctan2(s * c0 - c * s0, c * c0 + s * s0)
    return L - lead * beta / (2 * np.pi)


def scipy_forward(table: Table, commands: np.ndarray) -> np.ndarray:
    """Baseline: forward kinematics pose by pose with scipy.optimize.fsolve on the numpy
    model (spiral term inside), from home, tolerance 1e-12."""
    from scipy.optimize import fsolve

    out = np.empty_like(commands)
    for i, cmd in enumerate(commands):
        out[i] = fsolve(
            lambda q, c=cmd: numpy_command(table, q[None])[0] - c, np.zeros(6), xtol=1e-12
        )
    return out


def numpy_design_criteria(
    table: Table,
    leg_stiffness: float,
    mass: float,
    accel: float,
    ell: float,
    inertia: np.ndarray,
    poses: np.ndarray,
) -> dict:
    """Baseline for the design criteria of one design over (N, 6) poses, vectorised numpy
    (np.linalg.svd / inv / solve / eigvalsh over the poses): worst and mean LCI, worst force
    stiffness, worst leg force (platform CoG at the origin), first frequency at home with the
    moving mass `mass` and principal inertia `inertia` (3,) kg·mm². A subset of jaxtable's
    criteria (no tolerance budget, no spiral error): the baseline does less work."""
    a = np.asarray(table.platform_joints)
    b = np.asarray(table.base_joints)

    def legs(q):
        R = numpy_rotation(q[:, 3:])
        t = q[:, :3] + np.array([0.0, 0.0, float(table.home_height)])
        ra = np.einsum("nij,kj->nki", R, a)
        l = t[:, None, :] + ra - b
        u = l / np.linalg.norm(l, axis=-1, keepdims=True)
        return np.concatenate([u, np.cross(ra, u)], axis=-1)  # (N, 6, 6) rows [u, Ra×u]

    J = legs(poses)
    sv = np.linalg.svd(J * np.r_[np.ones(3), np.full(3, 1 / ell)], compute_uv=False)
    lci = 6.0 / np.sqrt(np.sum(sv**2, axis=1) * np.sum(sv**-2.0, axis=1))  # 1/κ_F
    K = leg_stiffness * np.einsum("nki,nkj->nij", J, J)
    C = np.linalg.inv(K)
    k_t = 1.0 / np.linalg.eigvalsh(C[:, :3, :3])[:, -1]
    JT = np.transpose(J, (0, 2, 1))
    W = np.array([0.0, 0.0, -9.80665 * mass, 0.0, 0.0, 0.0])
    f0 = np.linalg.solve(JT, np.broadcast_to(W, (len(poses), 6))[..., None])[..., 0]
    G = np.concatenate([np.eye(3), np.zeros((3, 3))]) * (-mass * accel)
    B = np.linalg.solve(JT, np.broadcast_to(G, (len(poses), 6, 3)))
    force = np.abs(f0) + np.linalg.norm(B, axis=-1)
    M = np.diag(np.r_[mass, mass, mass, np.asarray(inertia, dtype=float)])
    K0 = leg_stiffness * legs(np.zeros((1, 6)))[0].T @ legs(np.zeros((1, 6)))[0]
    from scipy.linalg import eigh

    lam = eigh(K0, M, eigvals_only=True)[0]
    return {
        "min_lci": float(lci.min()),
        "gci": float(lci.mean()),
        "min_stiffness_translation_N_per_mm": float(k_t.min()),
        "max_leg_force_N": float(force.max()),
        "first_frequency_Hz": float(np.sqrt(1e3 * lam) / (2 * np.pi)),
    }
