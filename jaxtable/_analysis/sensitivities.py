"""Pose sensitivities to model parameters by autodiff, and the paper's analytic eq. (11).

The controller commands the nominal inverse kinematics s(q); the hardware's parameters differ
from nominal by δθ; the platform then settles at q + δq with, to first order,

    δq = −(∂r/∂q)⁻¹ (∂r/∂θ) δθ,      r(q, θ, s) = |l_i(q; θ)| − L0_i − s_i − Σ effects,

the implicit function theorem applied to the forward map at the commanded pose (the same
derivative `jax.jacfwd(forward)` gives through the Newton solve; the tests check both, and
finite differences). Poses are (..., 6); parameters are named leaves of the table or of an
effect ("base_joints", "zero_lengths", "lead", "spiral.lead", "lead_scale.eps", ...).
"""

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from .. import _params as params
from .._batch import flatten_batch, run_batch
from .._effects import Effects, resolve_effects
from .._errors import check_finite_poses, require_x64
from .._kinematics import leg_lines
from .._linalg import solve_small
from .._model import inverse_extension, length_residual
from .._rotation import euler_rate_matrix, rotation_matrix
from .._table import Table

GEOMETRY_42 = params.PAPER_42  # the paper's e_p order (kept for existing imports)


def _get(model, name: str):
    return params.get(model[0], model[1], name)


def check_parameter_names(model, wrt) -> None:
    """Raise ValueError naming any entry of `wrt` that is not a parameter of `model`."""
    params.check(model[0], model[1], wrt)


def parameter_names(model, wrt) -> list[str]:
    """Column names of the flattened parameters: legs 1-based, e.g. 'base_joints[2].y'."""
    return [k for name in wrt for k in params.element_keys(name, np.shape(_get(model, name)))]


def _flatten(model, wrt):
    leaves = [jnp.asarray(_get(model, n), dtype=jnp.float64) for n in wrt]
    shapes = [x.shape for x in leaves]
    theta = jnp.concatenate([x.reshape(-1) for x in leaves])

    def unflatten(theta):
        out, k = [], 0
        for shp in shapes:
            n = int(np.prod(shp))
            out.append(theta[k : k + n].reshape(shp))
            k += n
        return params.replace(model[0], model[1], dict(zip(wrt, out)))

    return theta, unflatten


def jacobians_one(table, effects, pose, wrt):
    """(∂r/∂q (6, 6), ∂r/∂θ (6, P)) at one commanded pose, with s the nominal command.
    `effects=None`: the table's hardware effects, rebuilt from the (differentiated) table so
    'lead' and 'hand' have derivatives."""
    model = (table, {} if effects is None else dict(effects))
    theta0, unflatten = _flatten(model, wrt)

    def residual(theta, q, s):
        t, eff = unflatten(theta)
        return length_residual(t, resolve_effects(t, effects if effects is None else eff), q, s)

    s, _ = inverse_extension(table, resolve_effects(table, effects), pose)
    Jq = jax.jacfwd(residual, argnums=1)(theta0, pose, s)
    Jt = jax.jacfwd(residual, argnums=0)(theta0, pose, s)
    return Jq, Jt


def per_leg_jacobians_one(table, effects, pose, wrt, s=None):
    """(∂r/∂q (6, 6), [∂r_i/∂θ_i (6, m) per name]) for per-leg parameters (leaves of shape
    (6,) or (6, m)), at one commanded pose.

    Leg i's residual depends only on leg i's parameters, so one forward-mode tangent per
    column of a leaf (perturbing that column on every leg at once) gives all of them: m
    tangents per leaf instead of 6·m. Row i of the result is ∂r_i/∂θ_i. Same maths as
    `jacobians_one`, fewer tangents; the tests check they agree. `s`: the nominal extensions
    when the caller has them (default: the inverse solve)."""
    model = (table, {} if effects is None else dict(effects))
    leaves = [jnp.asarray(_get(model, n), dtype=jnp.float64) for n in wrt]
    widths = [1 if x.ndim == 1 else x.shape[1] for x in leaves]
    offsets = np.cumsum([0] + widths)

    def perturbed(c):
        new = []
        for x, w, o in zip(leaves, widths, offsets):
            d = c[o : o + w]
            new.append(x + (d[0] if x.ndim == 1 else d[None, :]))
        return params.replace(model[0], model[1], dict(zip(wrt, new)))

    def residual(c, q, s):
        t, eff = perturbed(c)
        return length_residual(t, resolve_effects(t, effects if effects is None else eff), q, s)

    if s is None:
        s, _ = inverse_extension(table, resolve_effects(table, effects), pose)
    c0 = jnp.zeros(int(offsets[-1]))
    Jq = jax.jacfwd(residual, argnums=1)(c0, pose, s)
    Jc = jax.jacfwd(residual, argnums=0)(c0, pose, s)
    return Jq, [Jc[:, o : o + w] for w, o in zip(widths, offsets)]


def sensitivity_one(table, effects, pose, wrt, rotation_vector: bool):
    """d(actual pose)/dθ at one commanded pose, (6, P): −(∂r/∂q)⁻¹ ∂r/∂θ."""
    Jq, Jt = jacobians_one(table, effects, pose, wrt)
    dq = -solve_small(Jq, Jt)  # plain jnp: no LAPACK call in batched kernels (see _linalg)
    if rotation_vector:
        dq = jnp.concatenate([dq[:3], euler_rate_matrix(pose[3:]) @ dq[3:]])
    return dq


def _sensitivity_row(shared, pose):
    table, effects, wrt, rotation_vector = shared
    return sensitivity_one(table, effects, pose, wrt, rotation_vector)


def pose_sensitivity(
    table: Table,
    poses,
    wrt=GEOMETRY_42,
    *,
    effects: Effects | None = None,
    rotation_vector: bool = False,
    chunk: int = 1 << 14,
) -> tuple[Float[ArrayLike, "... 6 P"], list[str]]:
    """Sensitivity of the actual pose to parameters at commanded `poses` (..., 6).

    Returns (J, names): J (..., 6, P) with rows (x, y, z in mm; then either Euler-angle
    increments d(roll, pitch, yaw) in rad, or with `rotation_vector=True` the small rotation
    vector dΩ in the base frame, rad, as the paper's eq. (11) uses), columns the flattened
    parameters named in `names`. `wrt`: table leaves and/or "effect.field" names; default the
    paper's 42 geometric parameters in its order [dl (6), da^p (18), db (18)].
    """
    require_x64()
    check_finite_poses(poses)
    wrt = tuple(wrt)
    model = (table, {} if effects is None else dict(effects))
    check_parameter_names(model, wrt)
    names = parameter_names(model, wrt)
    flat, batch_shape = flatten_batch(poses, 1)
    shared = (table, None if effects is None else dict(effects), wrt, rotation_vector)
    J = jnp.asarray(run_batch(_sensitivity_row, shared, flat, chunk=chunk))
    return J.reshape(batch_shape + J.shape[1:]), names


def paper_error_jacobian_one(table: Table, pose: Float[ArrayLike, "6"]) -> Float[ArrayLike, "6 42"]:
    """The paper's eq. (11), e = J_lx⁻¹ J_s, at one pose: (6, 42), rows [dt (mm); dΩ (rad,
    small rotation vector, base frame)], columns [dl_1..6, da_1^p..da_6^p (xyz), db_1..db_6
    (xyz)]. J_lx rows [u_iᵀ, (R a_i^p × u_i)ᵀ]; J_s rows [1, −u_iᵀR, u_iᵀ] (rigid geometry)."""
    u, moment = leg_lines(table, pose)
    R = rotation_matrix(pose[3:])
    J_lx = jnp.concatenate([u, moment], axis=1)
    eye = jnp.eye(6)
    J_dl = eye
    J_da = -(eye[:, :, None] * (u @ R)[:, None, :]).reshape(6, 18)
    J_db = (eye[:, :, None] * u[:, None, :]).reshape(6, 18)
    J_s = jnp.concatenate([J_dl, J_da, J_db], axis=1)
    return jnp.linalg.solve(J_lx, J_s)


def paper_error_jacobian(table: Table, poses) -> Float[ArrayLike, "... 6 42"]:
    """Batched `paper_error_jacobian_one`: (..., 6) -> (..., 6, 42)."""
    from .._api import per_pose

    return per_pose(paper_error_jacobian_one, table, poses, 1 << 16)
