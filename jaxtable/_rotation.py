"""Rotation matrices for the Z-Y-X (yaw-pitch-roll) attitude convention."""

import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._linalg import computed_once

ARCSEC_PER_RAD = math.degrees(1.0) * 3600.0


def rotation_entries(
    angles: Float[ArrayLike, "3"], once: bool = False
) -> tuple[tuple[Array, Array, Array], ...]:
    """The nine entries of `rotation_matrix` as a row-major tuple of scalar tuples.

    Kept unstacked so that under `vmap` each entry is one elementwise expression fused into
    its consumer (a stacked matrix becomes separate fusions that each recompute the sines).
    `once=True`: the six sines and cosines are each computed once per kernel
    (`_linalg.computed_once`), for kernels whose many fusions read R (the error map's, where
    XLA otherwise recomputed them in ~10 fusions); not for the pose -> command map, which
    fuses into one loop anyway.
    """
    phi, theta, psi = angles[0], angles[1], angles[2]
    cf, sf = jnp.cos(phi), jnp.sin(phi)
    ct, st = jnp.cos(theta), jnp.sin(theta)
    cp, sp = jnp.cos(psi), jnp.sin(psi)
    if once:
        cf, sf, ct, st, cp, sp = (computed_once(v) for v in (cf, sf, ct, st, cp, sp))
    return (
        (cp * ct, cp * st * sf - sp * cf, cp * st * cf + sp * sf),
        (sp * ct, sp * st * sf + cp * cf, sp * st * cf - cp * sf),
        (-st, ct * sf, ct * cf),
    )


def rotation_matrix(angles: Float[ArrayLike, "3"]) -> Float[ArrayLike, "3 3"]:
    """R = Rz(yaw) @ Ry(pitch) @ Rx(roll), platform frame -> base frame.

    **Arguments:** `angles`: (roll, pitch, yaw) = (φ, θ, ψ) in radians, shape (3,).

    **Returns:** the 3×3 rotation matrix. A vector `a_p` fixed in the platform has base-frame
    coordinates `R @ a_p`. This is the paper's Z-Y-X order written correctly (its eq. (2) has
    three misprinted elements; see `paper_rotation_matrix`).
    """
    return jnp.array(rotation_entries(angles))


def euler_matrices(angles: np.ndarray, order: str = "zyx", signs=(1, 1, 1)) -> np.ndarray:
    """Rotation matrices (N, 3, 3) of attitudes `angles` (N, 3) = (roll, pitch, yaw), rad,
    composed in another convention: the product of the axis rotations in `order` from left
    to right ("zyx": Rz(yaw) Ry(pitch) Rx(roll), `rotation_matrix`'s; "xyz": Rx(roll)
    Ry(pitch) Rz(yaw)), each angle times its sign in `signs` (roll, pitch, yaw: −1 for an
    angle measured in the other sense). numpy in, numpy out: for reading other
    instruments' files, never for kinematics."""
    a = np.asarray(angles, float) * np.asarray(signs, float)
    out = np.broadcast_to(np.eye(3), (len(a), 3, 3))
    for letter in order:  # three factors, not a loop over attitudes
        out = out @ _axis_rotations(a, "xyz".index(letter))
    return out


def _axis_rotations(a: np.ndarray, k: int) -> np.ndarray:
    """(N, 3, 3) the rotations about axis k (0, 1, 2: x, y, z) by the angles a[:, k]."""
    i, j = [(1, 2), (2, 0), (0, 1)][k]
    c, s = np.cos(a[:, k]), np.sin(a[:, k])
    m = np.zeros((len(a), 3, 3))
    m[:, k, k] = 1.0
    m[:, i, i] = m[:, j, j] = c
    m[:, i, j], m[:, j, i] = -s, s
    return m


def best_rotation(P: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, S): the rotation R (3, 3) minimising Σ |R p_k − q_k|² over rows of P, Q (K, 3)
    (Kabsch: from the SVD of Pᵀ Q, its sign fixed so that det R = +1), and the singular
    values S (3,) of Pᵀ Q (S[1] ≈ 0: the rows lie on a line and R is not determined about
    it). numpy in, numpy out."""
    U, S, Vt = np.linalg.svd(np.asarray(P, float).T @ np.asarray(Q, float))
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T, S


def paper_rotation_matrix(angles: Float[ArrayLike, "3"]) -> Float[ArrayLike, "3 3"]:
    """The paper's eq. (2) exactly as printed, typos included. For comparison only.

    Elements (1,3), (2,2) and (2,3) (1-based) are misprinted; the matrix is in general not a
    rotation. Never use it for kinematics.
    """
    phi, theta, psi = angles[0], angles[1], angles[2]
    cf, sf = jnp.cos(phi), jnp.sin(phi)
    ct, st = jnp.cos(theta), jnp.sin(theta)
    cp, sp = jnp.cos(psi), jnp.sin(psi)
    return jnp.array(
        [
            [cp * ct, cp * st * sf - sp * cf, sp * sf - sp * st * cf],
            [sp * ct, cp * cf - sp * st * sf, cp * st * cf - cp * sf],
            [-st, ct * sf, ct * cf],
        ]
    )


def euler_rate_matrix(angles: Float[ArrayLike, "3"]) -> Float[ArrayLike, "3 3"]:
    """E(φ, θ, ψ) with ω = E @ (dφ, dθ, dψ): Z-Y-X Euler-angle rates to the base-frame angular
    velocity (equivalently, small Euler increments to the small rotation vector).

    At zero attitude E is the identity, which is the paper's eq. (6)-(7) assumption.
    """
    theta, psi = angles[1], angles[2]
    ct, st = jnp.cos(theta), jnp.sin(theta)
    cp, sp = jnp.cos(psi), jnp.sin(psi)
    return jnp.array(
        [
            [cp * ct, -sp, 0.0],
            [sp * ct, cp, 0.0],
            [-st, 0.0, 1.0],
        ]
    )


def euler_from_matrix(R: Float[ArrayLike, "3 3 ..."]) -> Float[ArrayLike, "3 ..."]:
    """(roll, pitch, yaw) of R = Rz(yaw) Ry(pitch) Rx(roll), rad, shape (3,); the inverse of
    `rotation_matrix` for pitch in (−π/2, π/2). Trailing axes batch (R (3, 3, N) -> (3,
    N)); numpy in, numpy out."""
    xp = np if isinstance(R, np.ndarray) else jnp
    return xp.stack(
        [
            xp.arctan2(R[2, 1], R[2, 2]),
            -xp.arcsin(xp.clip(R[2, 0], -1.0, 1.0)),
            xp.arctan2(R[1, 0], R[0, 0]),
        ]
    )


def rotation_log(R: Float[ArrayLike, "*batch 3 3"]) -> Float[ArrayLike, "*batch 3"]:
    """Rotation vector ω (rad, shape (3,)) with R = exp([ω]×): the SO(3) log map. The angle
    is atan2 of the skew and symmetric parts, so it is accurate at every angle below π, and
    the small-angle branch keeps the gradient finite at the identity. Leading axes batch
    (R (..., 3, 3) -> ω (..., 3)); numpy in, numpy out (for checks on files, which would
    otherwise compile a program for every batch size)."""
    xp = np if isinstance(R, np.ndarray) else jnp
    w = 0.5 * xp.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
        axis=-1,
    )
    sin = xp.sqrt(xp.sum(w * w, axis=-1))
    cos = 0.5 * (R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0)
    small = sin < 1e-12
    safe = xp.where(small, 1.0, sin)
    scale = xp.where(small, 1.0 + sin**2 / 6, xp.arctan2(sin, cos) / safe)
    return w * scale[..., None]


def pose_error(
    actual: Float[ArrayLike, "6"], commanded: Float[ArrayLike, "6"]
) -> Float[ArrayLike, "6"]:
    """The error of pose `actual` against `commanded` (both (x, y, z, roll, pitch, yaw), mm /
    rad), shape (6,): translation difference (mm, base frame), then the rotation vector of
    R(actual) R(commanded)ᵀ (rad, base frame; `rotation_log`).

    This is jaxtable's one pose-error measure: every report, error map and Monte Carlo
    result uses it. It is an angle whatever the attitude, unlike a difference of Euler
    angles, which it equals to first order at zero attitude only.
    """
    D = rotation_matrix(actual[3:]) @ rotation_matrix(commanded[3:]).T
    return jnp.concatenate([actual[:3] - commanded[:3], rotation_log(D)])


def wrap_reading_difference(diff: Float[ArrayLike, "... 6"]) -> Float[ArrayLike, "... 6"]:
    """A difference of two readings (..., 6) (x, y, z, roll, pitch, yaw; mm / rad) with its
    angle columns wrapped to [−π, π): a residual of Euler-angle columns. numpy in, numpy
    out (no compiled program for a host array)."""
    xp = np if isinstance(diff, np.ndarray) else jnp
    diff = xp.asarray(diff)
    angles = xp.mod(diff[..., 3:] + np.pi, 2 * np.pi) - np.pi
    return xp.concatenate([diff[..., :3], angles], axis=-1)
