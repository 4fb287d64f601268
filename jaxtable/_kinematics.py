"""The pose -> leg map for ONE pose: leg vectors, lengths, rod rotation, joint bends.

Every function here takes a single pose q = (x, y, z, roll, pitch, yaw) (mm, rad), shape (6,),
and returns per-leg values with leading axis 6. The public batched versions in `_api.py`
wrap them with `jax.vmap`.
"""

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from ._errors import is_concrete
from ._jit import device_array
from ._linalg import computed_once
from ._rotation import rotation_entries, rotation_matrix
from ._table import Table

HOME = device_array(np.zeros(6))

# Six 3-vectors are carried as a tuple of components (x, y, z), each of shape (6,): under
# `vmap` every operation below is then elementwise on (N, 6) arrays, which XLA fuses into one
# loop (no dot products over a minor axis of 3, no stacking). This is the layout that makes
# the batched pose -> command map run at the transcendental-function limit (see the
# benchmark); `leg_vectors` stacks the components for callers that want (6, 3).
Vec3 = tuple[Array, Array, Array]


def _columns(v: Float[ArrayLike, "6 3"]) -> Vec3:
    return v[:, 0], v[:, 1], v[:, 2]


def _rotate(R, v: Vec3) -> Vec3:
    """R v for R given as nested row tuples (`rotation_entries`) or a (3, 3) array."""
    x, y, z = v
    return tuple(R[r][0] * x + R[r][1] * y + R[r][2] * z for r in range(3))


def _dot(a: Vec3, b: Vec3) -> Array:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a: Vec3, b: Vec3) -> Vec3:
    return (
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    )


def platform_origin(table: Table, pose: Float[ArrayLike, "6"]) -> Float[ArrayLike, "3"]:
    """t = (x, y, home_height + z), base frame, mm."""
    return pose[:3] + jnp.array([0.0, 0.0, 1.0]) * table.home_height


def _legs(table: Table, pose: Float[ArrayLike, "6"], R) -> Vec3:
    """Components of l_i = t + R a_i^p - b_i, each (6,), mm."""
    a = _rotate(R, _columns(table.platform_joints))
    b = _columns(table.base_joints)
    t = (pose[0], pose[1], pose[2] + table.home_height)
    return tuple(t[k] + a[k] - b[k] for k in range(3))


def leg_vectors(table: Table, pose: Float[ArrayLike, "6"]) -> Float[ArrayLike, "6 3"]:
    """l_i = t + R a_i^p - b_i, base frame, mm. Shape (6, 3)."""
    return jnp.stack(_legs(table, pose, rotation_entries(pose[3:])), axis=-1)


def leg_lengths(table: Table, pose: Float[ArrayLike, "6"]) -> Float[ArrayLike, "6"]:
    """|l_i|, joint-to-joint length of each leg, mm. Shape (6,)."""
    l = _legs(table, pose, rotation_entries(pose[3:]))
    return jnp.sqrt(_dot(l, l))


def _twist_sin_cos(table: Table, pose: Float[ArrayLike, "6"]):
    """(s, c) = r (sin β, cos β), r > 0, for the angle β between the planes (u, n) and (u, j)
    about the unit leg axis u = l/|l|, n the base joint's base-fixed axis and j = R j^p the
    platform joint's platform-fixed axis. Shapes (6,), (6,).

    With m = n×u and k = j×u, β is defined by sin β ∝ u·(m×k) and cos β ∝ m·k. By the
    vector identities (n×u)×(j×u) = −u ((n×u)·j) and (n×u)·(j×u) = n·j − (n·u)(j·u):
    u·(m×k) = (n×j)·u and m·k = n·j − (n·u)(j·u). Multiplying both by |l|² > 0 gives
    s = |l| (n×j)·l and c = (n·j)|l|² − (n·l)(j·l): polynomial in l except one sqrt.
    """
    R = rotation_entries(pose[3:])
    return _twist_sin_cos_of(
        table, _legs(table, pose, R), _rotate(R, _columns(table.platform_axes))
    )


def _twist_sin_cos_of(table: Table, l: Vec3, j: Vec3):
    """`_twist_sin_cos` from the leg vectors `l` and the platform axes `j` (base frame)."""
    n = _columns(table.base_axes)
    ll = _dot(l, l)
    s = jnp.sqrt(ll) * _dot(_cross(n, j), l)
    c = _dot(n, j) * ll - _dot(n, l) * _dot(j, l)
    return s, c


def twist_gradients(table: Table, l: Vec3, j: Vec3, once: bool = False) -> tuple[Vec3, Vec3]:
    """Gradients of the twist angle β of `_twist_sin_cos` at leg vectors `l` and platform
    axes `j` (base frame, components (6,) each): (∂β/∂l, ∂β/∂j), rad/mm and rad per unit.

    With w = n×j, L = |l|: S = L w·l, C = (n·j)L² − (n·l)(j·l), dβ = (C dS − S dC)/(S² + C²),
    ∇_l S = (w·l/L) l + L w, ∇_l C = 2(n·j) l − (j·l) n − (n·l) j, ∇_j S = L (l×n),
    ∇_j C = L² n − (n·l) l. Closed form for the first-order budget (no autodiff tangents);
    the tests check it against `jax.jacfwd` of `rod_rotation`. `once=True`: the per-leg
    scalars the six components share are each computed once per kernel
    (`_linalg.computed_once`), not again in every fusion that reads a component."""
    n = _columns(table.base_axes)
    w = _cross(n, j)
    ll = _dot(l, l)
    L = jnp.sqrt(ll)
    wl, nj, nl, jl = _dot(w, l), _dot(n, j), _dot(n, l), _dot(j, l)
    S = L * wl
    C = nj * ll - nl * jl
    inv = 1.0 / (S * S + C * C)
    S, C = S * inv, C * inv
    if once:
        S, C, L, wl, nj, nl, jl, ll = (computed_once(x) for x in (S, C, L, wl, nj, nl, jl, ll))
    ln = _cross(l, n)
    grad_l = tuple(
        C * (wl / L * l[k] + L * w[k]) - S * (2 * nj * l[k] - jl * n[k] - nl * j[k])
        for k in range(3)
    )
    grad_j = tuple(C * L * ln[k] - S * (ll * n[k] - nl * l[k]) for k in range(3))
    return grad_l, grad_j


def rod_rotation(table: Table, pose: Float[ArrayLike, "6"]) -> Float[ArrayLike, "6"]:
    """Δα_i: rotation of each rod relative to its barrel since home, rad. Shape (6,).

    Right-hand rule about the leg axis u_i (pointing base joint -> platform joint): positive is
    counter-clockwise seen from the platform end looking down the leg toward the base.
    Computed as one atan2 of the increment β(q) − β(home), so it never wraps at ±180° and has
    finite gradients everywhere except where a joint axis is parallel to its leg.
    """
    return twist_from_home(table, *_twist_sin_cos(table, pose))


def twist_from_home(table: Table, s, c):
    """`rod_rotation` from the twist's (s, c) (`_twist_sin_cos`) at the pose, rad, (6,)."""
    s0, c0 = _twist_sin_cos(table, HOME)
    r0 = jnp.sqrt(s0 * s0 + c0 * c0)
    s0, c0 = s0 / r0, c0 / r0
    return jnp.arctan2(s * c0 - c * s0, c * c0 + s * s0)


def spiral_extension(table: Table, pose: Float[ArrayLike, "6"]) -> Float[ArrayLike, "6"]:
    """Δl2_i = hand_i · lead_i · Δα_i / (2π): passive extension from the rod rotation, mm."""
    return table.signed_lead * rod_rotation(table, pose) / (2 * jnp.pi)


def paper_rod_rotation(table: Table, pose: Float[ArrayLike, "6"]) -> Float[ArrayLike, "6"]:
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


def leg_lines(
    table: Table, pose: Float[ArrayLike, "6"]
) -> tuple[Float[ArrayLike, "6 3"], Float[ArrayLike, "6 3"]]:
    """The legs as lines (Plücker coordinates, base frame): unit directions u_i (6, 3) and
    moment arms R a_i^p × u_i (6, 3), mm. Row i of [u, R a × u] is row i of the rigid
    kinematic Jacobian ∂L/∂(t, ω) and column i of the static wrench map of leg forces."""
    l = leg_vectors(table, pose)
    u = l / jnp.linalg.norm(l, axis=-1, keepdims=True)
    ra = table.platform_joints @ rotation_matrix(pose[3:]).T
    return u, jnp.cross(ra, u)


def in_stroke(table: Table, lengths: Float[ArrayLike, "... 6"]) -> Bool[ArrayLike, "... 6"]:
    """Elementwise: each joint-to-joint length (mm) inside the table's stroke [lo, hi]. A
    numpy `lengths` with a concrete table is checked in numpy (the input checks of the batch
    APIs: eagerly, jnp compiled a small program per array shape)."""
    if isinstance(lengths, np.ndarray) and is_concrete(table.stroke):
        lo, hi = np.asarray(table.stroke, dtype=float)
        return (lengths >= lo) & (lengths <= hi)
    lengths = jnp.asarray(lengths)
    return (lengths >= table.stroke[0]) & (lengths <= table.stroke[1])


def _angle(a: Vec3, b: Vec3) -> Array:
    c = _cross(a, b)
    return jnp.arctan2(jnp.sqrt(_dot(c, c)), _dot(a, b))


def _legs_from_home(table: Table, pose: Float[ArrayLike, "6"], once: bool = False):
    """(|l_i|, u_i, Rᵀu_i, u_i(0)): leg lengths (6,) mm and unit leg directions, each a
    tuple of three (6,) components: in the base frame now, in the platform frame now, and
    at home (the U-joints' neutral direction). `once`: as for `rotation_entries`."""
    R = rotation_entries(pose[3:], once)
    l = _legs(table, pose, R)
    L = jnp.sqrt(_dot(l, l))
    u = tuple(x / L for x in l)
    l0 = _legs(table, HOME, rotation_entries(HOME[3:]))
    L0 = jnp.sqrt(_dot(l0, l0))
    u0 = tuple(x / L0 for x in l0)
    up = tuple(R[0][k] * u[0] + R[1][k] * u[1] + R[2][k] * u[2] for k in range(3))  # Rᵀu
    return L, u, up, u0


def _lengths_and_bends(table: Table, pose: Float[ArrayLike, "6"]):
    """(|l_i|, base bend, platform bend), (6,) each: see `joint_bend`."""
    L, u, up, u0 = _legs_from_home(table, pose)
    return L, _angle(u, u0), _angle(up, u0)


def joint_bend(table: Table, pose: Float[ArrayLike, "6"]) -> Float[ArrayLike, "2 6"]:
    """U-joint bend angles from the home leg direction, rad. Shape (2, 6): (base, platform).

    A U-joint is taken to be mounted with its neutral direction along the leg at home; the
    base bend is the angle between u_i(q) and u_i(0) in the base frame, the platform bend the
    angle between Rᵀu_i(q) and u_i(0) in the platform frame.
    """
    return jnp.stack(_lengths_and_bends(table, pose)[1:])


def within_limits(table: Table, pose: Float[ArrayLike, "6"], once: bool = False) -> Array:
    """True when every leg length |l_i| is inside the stroke and every U-joint bend is within
    the table's joint angle limit (bool scalar). `once`: as for `rotation_entries`."""
    # bend ≤ limit compared as cosines, cos(bend) = u·u0 ≥ cos(limit) (no arctangent: the
    # error map's kernel checks every pose)
    L, u, up, u0 = _legs_from_home(table, pose, once)
    limit = table.joint_angle_limit
    c = jnp.cos(jnp.minimum(limit, jnp.pi))
    bend_ok = (limit >= jnp.pi) | ((_dot(u, u0) >= c) & (_dot(up, u0) >= c))
    return jnp.all(in_stroke(table, L) & bend_ok)
