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


def _legs_and_twist(table: Table, t: np.ndarray, R: np.ndarray, a=None, b=None) -> tuple:
    """Leg lengths |l_i| (N, 6) and the rod twist's sine and cosine terms u·(m×k), m·k
    (N, 6) with m = n×u, k = j×u (the paper's), at translations t (N, 3) from home and
    rotations R (N, 3, 3); `a`, `b`: platform and base joints (default the table's)."""
    a = np.asarray(table.platform_joints) if a is None else a
    b = np.asarray(table.base_joints) if b is None else b
    up = np.array([0.0, 0.0, float(table.home_height)])
    l = (t + up)[:, None, :] + np.einsum("nij,kj->nki", R, a) - b
    L = np.linalg.norm(l, axis=-1)
    u = l / L[..., None]
    m = np.cross(np.asarray(table.base_axes), u)
    k = np.cross(np.einsum("nij,kj->nki", R, np.asarray(table.platform_axes)), u)
    return L, np.sum(u * np.cross(m, k), -1), np.sum(m * k, -1)


def _twist_from_home(table: Table, t, R, a=None, b=None) -> tuple:
    """(|l_i|, the rod twist Δα_i from home in rad), (N, 6) each (`_legs_and_twist`)."""
    L, s, c = _legs_and_twist(table, t, R, a, b)
    _, s0, c0 = _legs_and_twist(table, np.zeros((1, 3)), np.eye(3)[None], a, b)
    return L, np.arctan2(s * c0 - c * s0, c * c0 + s * s0)


def numpy_command(table: Table, poses: np.ndarray) -> np.ndarray:
    """Baseline: compensated command |l_i| − lead·Δα_i/(2π), (N, 6) mm, vectorised numpy."""
    L, beta = _twist_from_home(table, poses[:, :3], numpy_rotation(poses[:, 3:]))
    return L - np.asarray(table.signed_lead) * beta / (2 * np.pi)


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


def numpy_error_map(table: Table, sigmas: np.ndarray, poses: np.ndarray, rho: float) -> tuple:
    """Baseline for the tolerance error map at (N, 6) commanded poses, vectorised numpy with
    central differences, as a numpy user would write it: the residual of each leg,
    r_i = |l_i| − L0_i − s_i − c_i Δα_i − ε_i s_i (s the nominal compensated command, fixed;
    c = lead / 2π; Δα the rod twist from home, both ends of it moved by a joint error), its
    pose Jacobian K in (t, ω) (ω the small rotation vector in the base frame) by central
    differences (h = 1e-3 mm, 1e-6 rad), the joints' gains by central differences of every
    leg's joint component at once (a leg's residual depends on its own joints only), the
    linear ones in closed form (L0: 1; ε: s²; the lead: (Δα / 2π)²); σ per source from
    `np.linalg.inv(K)`. `sigmas` (6,): σ per source in model units, ordered as
    `jaxtable`'s sources (base joints, platform joints, zero length, lead error, clearance,
    spiral lead). `rho`: the platform radius, mm.

    Returns (std (N, 7, 6): per source and the total, x y z mm and the rotation vector rad;
    bias (N, 6): the pose error of an uncompensated command, K⁻¹ c Δα; cond (N,): the
    2-norm condition number (`np.linalg.cond`) of the Euler-angle Jacobian with its angle
    columns divided by `rho`). Less work than jaxtable's map: no reachability, no summary."""
    a0 = np.asarray(table.platform_joints)
    b0 = np.asarray(table.base_joints)
    c = np.asarray(table.signed_lead) / (2 * np.pi)
    L0 = np.asarray(table.zero_lengths)

    def extension(t, R, a=a0, b=b0):  # |l| − L0 − c Δα and Δα, (N, 6) each
        L, turn = _twist_from_home(table, t, R, a, b)
        return L - L0 - c * turn, turn

    t, R = poses[:, :3], numpy_rotation(poses[:, 3:])
    s, turn = extension(t, R)  # the nominal command; r = extension − s − ε s
    n = len(poses)

    def rotated(w):  # R turned by the small rotation vector w (3,) in the base frame
        th = np.linalg.norm(w)
        k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]) / th
        return (np.eye(3) + np.sin(th) * k + (1 - np.cos(th)) * k @ k) @ R

    def rotated_euler(i, h):
        q = poses[:, 3:].copy()
        q[:, i] += h
        return numpy_rotation(q)

    ht, hw = 1e-3, 1e-6
    K = np.empty((n, 6, 6))  # rows: legs; columns: t, ω
    Ke = np.empty((n, 6, 3))  # columns: Euler angles
    gains = np.zeros((n, 6, 6))  # (pose, leg, source)
    for i in range(3):  # x, y, z of a translation, a rotation, an Euler angle and the joints
        e, w = np.eye(3)[i] * ht, np.eye(3)[i] * hw
        K[:, :, i] = (extension(t + e, R)[0] - extension(t - e, R)[0]) / (2 * ht)
        K[:, :, 3 + i] = (extension(t, rotated(w))[0] - extension(t, rotated(-w))[0]) / (2 * hw)
        Ke[:, :, i] = (
            extension(t, rotated_euler(i, hw))[0] - extension(t, rotated_euler(i, -hw))[0]
        ) / (2 * hw)
        gains[:, :, 0] += (
            (extension(t, R, b=b0 + e)[0] - extension(t, R, b=b0 - e)[0]) / (2 * ht)
        ) ** 2
        gains[:, :, 1] += (
            (extension(t, R, a=a0 + e)[0] - extension(t, R, a=a0 - e)[0]) / (2 * ht)
        ) ** 2
    gains[:, :, 2] = gains[:, :, 4] = 1.0  # L0 (zero length; clearance as an L0 error)
    gains[:, :, 3] = s**2  # ε
    gains[:, :, 5] = (turn / (2 * np.pi)) ** 2  # the lead
    Kinv = np.linalg.inv(K)
    var = np.einsum("npi,nis->nsp", Kinv**2, gains) * np.asarray(sigmas)[None, :, None] ** 2
    std = np.sqrt(np.concatenate([var, var.sum(1, keepdims=True)], axis=1))
    bias = np.einsum("npi,ni->np", Kinv, c * turn)
    cond = np.linalg.cond(np.concatenate([K[:, :, :3], Ke / rho], axis=2))
    return std, bias, cond
