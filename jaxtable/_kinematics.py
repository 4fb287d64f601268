"""The pose -> leg map for ONE pose: leg vectors, lengths, rod rotation, joint bends.

Every function here takes a single pose q = (x, y, z, roll, pitch, yaw) (mm, rad), shape (6,),
and returns per-leg values with leading axis 6. The public batched versions in `_api.py`
wrap them with `jax.vmap`.
"""

import jax.numpy as jnp
from jaxtyping import Array, Float

from ._rotation import rotation_matrix
from ._table import Table, home_leg_vectors

HOME = jnp.zeros(6)


def platform_origin(table: Table, pose: Float[Array, "6"]) -> Float[Array, "3"]:
    """t = (x, y, home_height + z), base frame, mm."""
    return pose[:3] + jnp.array([0.0, 0.0, 1.0]) * table.home_height


def leg_vectors(table: Table, pose: Float[Array, "6"]) -> Float[Array, "6 3"]:
    """l_i = t + R a_i^p - b_i, base frame, mm. Shape (6, 3)."""
    R = rotation_matrix(pose[3:])
    return platform_origin(table, pose) + table.platform_joints @ R.T - table.base_joints


def leg_lengths(table: Table, pose: Float[Array, "6"]) -> Float[Array, "6"]:
    """|l_i|, joint-to-joint length of each leg, mm. Shape (6,)."""
    return jnp.linalg.norm(leg_vectors(table, pose), axis=-1)


def _twist_sin_cos(table: Table, pose: Float[Array, "6"]):
    """(s, c) = (u·(m×k), m·k) with m = n×u, k = j×u, unnormalised. Shapes (6,), (6,).

    s = r sin β, c = r cos β with r = |n×u||j×u| > 0, so atan2(s, c) = β exactly.
    """
    l = leg_vectors(table, pose)
    u = l / jnp.linalg.norm(l, axis=-1, keepdims=True)
    R = rotation_matrix(pose[3:])
    n = table.base_axes
    j = table.platform_axes @ R.T
    m = jnp.cross(n, u)
    k = jnp.cross(j, u)
    s = jnp.sum(u * jnp.cross(m, k), axis=-1)
    c = jnp.sum(m * k, axis=-1)
    return s, c


def rod_rotation(table: Table, pose: Float[Array, "6"]) -> Float[Array, "6"]:
    """Δα_i: rotation of each rod relative to its barrel since home, rad. Shape (6,).

    Right-hand rule about the leg axis u_i (pointing base joint -> platform joint): positive is
    counter-clockwise seen from the platform end looking down the leg toward the base.
    Computed as one atan2 of the increment, so it never wraps at ±180° and has finite
    gradients everywhere except where a joint axis is parallel to its leg.
    """
    s, c = _twist_sin_cos(table, pose)
    s0, c0 = _twist_sin_cos(table, HOME)
    return jnp.arctan2(s * c0 - c * s0, c * c0 + s * s0)


def spiral_extension(table: Table, pose: Float[Array, "6"]) -> Float[Array, "6"]:
    """Δl2_i = hand_i · lead_i · Δα_i / (2π): passive extension from the rod rotation, mm."""
    return table.signed_lead * rod_rotation(table, pose) / (2 * jnp.pi)


def paper_rod_rotation(table: Table, pose: Float[Array, "6"]) -> Float[Array, "6"]:
    """The paper's eqs. (15)-(19) taken literally, rad. Shape (6,). For comparison only.

    k_i = j_i × l_i / |l_i|, m_i = n_i × l_i / |l_i| (not unit unless the axis is perpendicular
    to the leg), α_i = arccos(k_i · m_i), n_i's sign flipped where the home angle α_i0 > 90°,
    Δα_i = (α_i − α_i0) · sign((k_i × m_i) · z). Its sense is the opposite of `rod_rotation`
    (sign from k×m, not m×k, viewed along +z): where both are valid, paper = −rod_rotation.
    Errs when the axes are not perpendicular to the leg (biased arccos), when a leg points
    downward (z sign test), when the twist passes through k ∥ m, and its gradient is infinite
    at k · m = ±1 (at home when α_i0 = 0).
    """

    def angle_and_sign(q, flip):
        l = leg_vectors(table, q)
        lnorm = jnp.linalg.norm(l, axis=-1, keepdims=True)
        R = rotation_matrix(q[3:])
        n = table.base_axes * flip[:, None]
        j = table.platform_axes @ R.T
        k = jnp.cross(j, l) / lnorm
        m = jnp.cross(n, l) / lnorm
        alpha = jnp.arccos(jnp.clip(jnp.sum(k * m, axis=-1), -1.0, 1.0))
        sign = jnp.sign(jnp.cross(k, m)[:, 2])
        return alpha, sign

    alpha0, _ = angle_and_sign(HOME, jnp.ones(6))
    flip = jnp.where(alpha0 > jnp.pi / 2, -1.0, 1.0)
    alpha0, _ = angle_and_sign(HOME, flip)
    alpha, sign = angle_and_sign(pose, flip)
    return (alpha - alpha0) * sign


def joint_bend(table: Table, pose: Float[Array, "6"]) -> Float[Array, "2 6"]:
    """U-joint bend angles from the home leg direction, rad. Shape (2, 6): (base, platform).

    A U-joint is taken to be mounted with its neutral direction along the leg at home; the
    base bend is the angle between u_i(q) and u_i(0) in the base frame, the platform bend the
    angle between Rᵀu_i(q) and u_i(0) in the platform frame.
    """
    l = leg_vectors(table, pose)
    u = l / jnp.linalg.norm(l, axis=-1, keepdims=True)
    l0 = home_leg_vectors(table)
    u0 = l0 / jnp.linalg.norm(l0, axis=-1, keepdims=True)
    R = rotation_matrix(pose[3:])
    up = u @ R  # rows: Rᵀ u_i

    def angle(a, b):
        return jnp.arctan2(jnp.linalg.norm(jnp.cross(a, b), axis=-1), jnp.sum(a * b, axis=-1))

    return jnp.stack([angle(u, u0), angle(up, u0)])
