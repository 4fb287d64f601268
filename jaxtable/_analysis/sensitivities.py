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
from .._jit import device_array
from .._kinematics import (
    HOME,
    _columns,
    _cross,
    _dot,
    _legs,
    _rotate,
    _twist_sin_cos_of,
    leg_lines,
    twist_from_home,
    twist_gradients,
)
from .._linalg import computed_once, solve_small
from .._model import inverse_extension, length_residual
from .._rotation import euler_rate_matrix, rotation_entries, rotation_matrix
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


BUDGET_WRT = params.GEOMETRY + ("lead_scale.eps", "spiral.lead")
"""The parameters of the tolerance budget, in the column order of `budget_jacobians_one`."""


def budget_jacobians_one(table: Table, pose: Float[ArrayLike, "6"]):
    """Closed-form first-order blocks of the budget model at one commanded pose: rigid legs,
    the table's own spiral term (lead `table.signed_lead`) and a zero lead-scale error
    (`tolerances.budget_effects`), r_i = |l_i| − L0_i − s_i − c_i Δα_i − ε_i s_i with
    c_i = lead_i/(2π) and s the nominal (compensated) command.

    Returns (s (6,) mm, K (6, 6), gains (6, 5), spiral (6,) mm):
    - K = ∂r/∂(t, ω): row i is [u_i − c_i g_i, (R a_i)×(u_i − c_i g_i) − c_i j_i×h_i], with
      u_i the unit leg, g_i = ∂β_i/∂l_i, h_i = ∂β_i/∂j_i (`twist_gradients`), ω the small
      rotation vector in the base frame (the Euler-angle Jacobian is K with its last three
      columns times `euler_rate_matrix`);
    - gains[i, k] = Σ_c (∂r_i/∂θ_ic)² over the components of leg i's parameter `BUDGET_WRT[k]`:
      b_i: |u_i − c_i(g_i − g0_i)|²; a_i^p: |Rᵀ(u_i − c_i g_i) + c_i g0_i|² (g0 at home, where
      the twist is measured from); L0_i: 1; ε_i: s_i²; lead_i: (Δα_i/2π)²;
    - spiral: Δl2_i = c_i Δα_i, the passive extension the command compensates.

    Leg i's residual depends only on leg i's parameters, which is why a gain per leg and
    parameter is all the budget needs. The same derivatives as `jacobians_one` on
    `budget_effects` (the tests compare them), without autodiff tangents: the error map's
    kernel runs several times faster."""
    # what many fusions read is computed once (`computed_once`): XLA would otherwise
    # recompute the sines, the legs and the twist geometry in each fusion that reads them
    R = rotation_entries(pose[3:], once=True)
    l = tuple(computed_once(x) for x in _legs(table, pose, R))
    ra = _rotate(R, _columns(table.platform_joints))
    j = tuple(computed_once(x) for x in _rotate(R, _columns(table.platform_axes)))
    l0 = _legs(table, HOME, rotation_entries(HOME[3:]))
    g, h = twist_gradients(table, l, j, once=True)
    g0, _ = twist_gradients(table, l0, _columns(table.platform_axes))
    L = jnp.sqrt(_dot(l, l))
    turns = twist_from_home(table, *_twist_sin_cos_of(table, l, j)) / (2 * jnp.pi)
    spiral = table.signed_lead * turns
    s = L - table.zero_lengths - spiral
    c = table.signed_lead / (2 * jnp.pi)
    # K's entries each written once: else every fusion that reads K (the budget's inverse,
    # the condition number's products) recomputes the leg and twist geometry behind them
    dt = tuple(computed_once(l[k] / L - c * g[k]) for k in range(3))
    m1, m2 = _cross(ra, dt), _cross(j, h)
    dw = tuple(computed_once(m1[k] - c * m2[k]) for k in range(3))
    db = tuple(-dt[k] - c * g0[k] for k in range(3))
    da = tuple(R[0][k] * dt[0] + R[1][k] * dt[1] + R[2][k] * dt[2] + c * g0[k] for k in range(3))
    K = jnp.stack(dt + dw, axis=1)
    gains = jnp.stack(
        [_dot(db, db), _dot(da, da), jnp.ones(6), s * s, turns * turns],
        axis=1,
    )
    return s, K, gains, spiral


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
    J = run_batch(_sensitivity_row, shared, flat, chunk=chunk)
    return device_array(J, batch_shape + np.shape(J)[1:]), names


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
