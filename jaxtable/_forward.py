"""Forward kinematics for ONE command: 6-D Newton with the effects inside."""

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import ArrayLike, Float, Int

from ._context import Context
from ._effects import Effects
from ._linalg import lu_small, lu_solve_small, solve_small
from ._model import length_residual
from ._table import Table

# The residual as a nested jit, for the solves that are differentiated (fits, Jacobians):
# traced once, then reused by the solve's several uses of it (first step, Newton and chord
# loops, final residual, the implicit derivative) and by their transformations, which JAX
# caches per traced program: a fit's tracing 10 -> 7.5 s. Not in the plain solve: the call
# boundary costs the batched forward kinematics ~10 % of its run time.
_length_residual_once = eqx.filter_jit(length_residual)


class RESULTS(optx.RESULTS):  # pyright: ignore
    """Outcome of a forward solve: optimistix's (and lineax's) results, plus jaxtable's own.
    Compare with `==` (`result == RESULTS.successful`), look a message up with
    `RESULTS[result]`; batched results compare elementwise."""

    residual_above_tolerance = (
        "converged to a pose whose leg-length residual is above the acceptance tolerance"
    )
    non_physical_assembly = "converged to a non-physical assembly (platform at or below the base)"


class ForwardOptions(eqx.Module):
    """Newton settings. The unknown is the pose with its angles multiplied by the platform
    radius, so both tolerances are in mm (for angles: mm of arc at the platform joints).
    Stopping rule (max norm): |Δy| < atol + rtol·|y| and |residual| < atol.

    `peel_first_step`: take the first Newton step before the loop. Same iterates, step count
    and result; when the whole batch starts from one guess and no effect couples the
    extensions into the Jacobian, that step's Jacobian and factorisation are computed once
    for the batch instead of per pose (forward kinematics ~20 % faster, +0.7 s compile).
    `None` (default) leaves the choice to the caller: `forward`/`forward_solve` turn it on
    for a guess shared by a large batch (see below); a single-pose solve takes no peeled step.

    `chord_below`: once a Newton step is shorter than this fraction of the platform radius
    (1e-3: 0.35 mm on the reference table), later steps reuse that step's factorisation
    (chord, or simplified Newton, steps: a residual and two triangular solves instead of a
    Jacobian and an elimination) while each step at least halves the one before; a pose
    whose chord step would not halve goes back to Newton steps. The stopping rule and
    acceptance are the same; the iterates differ from Newton's by rounding at convergence.
    `None` (default) leaves the choice to the caller: `forward`/`forward_solve` use
    `CHORD_BELOW` on a large batch; the single-pose solve inside fits uses none (its few
    poses start near their solution and compile time dominates there); 0.0 turns it off.

    Large batches only (`forward_solve`): both speed-ups pay where a batch's run time
    counts, from `_jit.LARGE_BATCH` (4096) rows. A smaller batch is compile-bound (its run
    takes milliseconds), and there the defaults give plain Newton steps in one loop, whose
    program compiles in ~40 % of the time of the three loops with the peeled step and the
    chord phase; the poses differ from those by rounding at convergence (~1e-13 mm)."""

    rtol: float = eqx.field(static=True, default=1e-13)
    atol: float = eqx.field(static=True, default=1e-10)
    max_steps: int = eqx.field(static=True, default=50)
    accept_residual: float = eqx.field(static=True, default=1e-8)
    peel_first_step: bool | None = eqx.field(static=True, default=None)
    chord_below: float | None = eqx.field(static=True, default=None)


CHORD_BELOW = 1e-3  # forward kinematics of a batch: 2.7 → 3.7×10⁵ poses/s (see ForwardOptions)


def platform_radius(table: Table) -> Float[ArrayLike, ""]:
    """Platform radius (mean |a_i^p|), mm: converts rad to mm of arc for the Newton unknown."""
    return jnp.mean(jnp.linalg.norm(table.platform_joints, axis=-1))


def _newton(table, effects, s, guess, ctx, options, residual=length_residual, factorization=False):
    """Newton's method on the scaled pose, written as one `lax.while_loop` whose body is
    the residual, its 6×6 Jacobian (one `jacfwd`, primal shared) and a fused elimination
    (`solve_small`); no derivative (see `forward_one`).

    The stopping rule is optimistix's Cauchy rule for `optx.Newton`: stop after the step
    from y_k when max|Δy / (atol + rtol·|y_k+1|)| < 1 and max|r(y_k)| < atol. Written out
    rather than through `optx.root_find` because this solve sits inside every batched map,
    fit and Jacobian: the loop compiles to a fifth of the code (compile time of every
    program that contains it) and runs ~1.5× faster per step. `residual`: `length_residual`
    or its nested jit (`_length_residual_once`).

    `factorization=True` (no chord phase): also returns the last Newton step's (LU, perm)
    and the unknown's scale (6,), for the implicit derivative (`_solve_jvp`). That step's
    Jacobian is the one at the last iterate but one, which the stopping rule puts within
    atol + rtol·|y| (~1e-10 mm) of the solution."""
    table, effects, s, guess, ctx = jax.lax.stop_gradient((table, effects, s, guess, ctx))
    scale = jnp.concatenate([jnp.ones(3), jnp.full(3, platform_radius(table))])

    def fn(y):
        r = residual(table, effects, y / scale, s, ctx)
        return r, r

    def cond(carry):
        y, k, done = carry[:3]
        return ~done & (k < options.max_steps) & jnp.all(jnp.isfinite(y))

    def converged(y_new, dy, r):
        small = jnp.max(jnp.abs(dy) / (options.atol + options.rtol * jnp.abs(y_new))) < 1
        return small & (jnp.max(jnp.abs(r)) < options.atol)

    def newton_step(y):
        """(y − Δy, Δy, r(y), LU, perm): one Newton step and the factorisation it used (the
        primal of `solve_small`; no derivative is taken through the loop)."""
        J, r = jax.jacfwd(fn, has_aux=True)(y)
        LU, perm = lu_small(J)
        dy = lu_solve_small(LU, perm, r[:, None])[:, 0]
        return y - dy, dy, r, LU, perm

    def body(carry):
        y_new, dy, r, LU, perm = newton_step(carry[0])
        out = (y_new, carry[1] + 1, converged(y_new, dy, r))
        return out + (LU, perm) if factorization else out

    n = guess.shape[0]
    start = (guess * scale, jnp.array(0), False)
    if factorization:  # an identity until a step has factorised (max_steps = 0)
        start += (jnp.eye(n, dtype=scale.dtype), jnp.arange(n, dtype=scale.dtype))
    if options.peel_first_step and options.max_steps > 0:
        start = body(start)  # under vmap, batched only in what depends on the batch
    if options.chord_below:
        if factorization:
            raise ValueError("the chord phase keeps no factorisation at the solution")
        start = _chord_phase(
            fn, newton_step, converged, start, cond, options.chord_below * scale[3]
        )
    y, steps, done, *last = jax.lax.while_loop(cond, body, start)
    resid = jnp.max(jnp.abs(fn(y)[0]))
    finite = jnp.all(jnp.isfinite(y))
    result = RESULTS.where(done, RESULTS.successful, RESULTS.max_steps_reached)
    result = RESULTS.where(finite, result, RESULTS.nonfinite)
    ok = result == RESULTS.successful
    result = RESULTS.where(
        ok & ~(resid <= options.accept_residual), RESULTS.residual_above_tolerance, result
    )
    # a failed solve returns the guess (flagged by its result), never NaN, so derivatives
    # and optimisers that probe far-away parameters stay finite
    q = jnp.where(ok, y / scale, guess)
    below = q[2] + table.home_height <= 0
    result = RESULTS.where(
        (result == RESULTS.successful) & below, RESULTS.non_physical_assembly, result
    )
    out = q, result, steps, jnp.where(ok, resid, jnp.inf)
    return out + (*last, scale) if factorization else out


def _chord_phase(fn, newton_step, converged, start, cond, below):
    """Newton steps until the step (max norm, scaled pose, mm) is shorter than `below`, then
    chord steps that reuse the last factorisation while each step is at most half the one
    before (`ForwardOptions.chord_below`). Returns the (y, k, done) carry for the Newton
    loop, which finishes whatever has not converged (a chord step that would not halve is
    not taken).

    Under `vmap` each loop runs until its slowest pose is through, so the two phases are
    separate loops: the Newton phase costs the batch's largest count of Newton steps
    (2 after the shared first step on the reference workspace), the chord phase its
    largest count of chord steps (2–3)."""

    def newton_body(carry):
        y_new, dy, r, LU, perm = newton_step(carry[0])
        return y_new, carry[1] + 1, converged(y_new, dy, r), LU, perm, jnp.max(jnp.abs(dy))

    def newton_cond(carry):
        y, k, done, _, _, last = carry
        return cond((y, k, done)) & (last >= below)

    def chord_body(carry):
        y, k, _, LU, perm, last = carry
        r = fn(y)[0]
        dy = lu_solve_small(LU, perm, r[:, None])[:, 0]
        size = jnp.max(jnp.abs(dy))
        take = size <= 0.5 * last
        y_new = jnp.where(take, y - dy, y)
        return (
            y_new,
            k + take,
            take & converged(y_new, dy, r),
            LU,
            perm,
            jnp.where(take, size, -1.0),
        )

    def chord_cond(carry):
        y, k, done, _, _, last = carry
        return cond((y, k, done)) & (last >= 0)

    y, k, done = start
    n = y.shape[0]
    inf = jnp.asarray(jnp.inf, y.dtype)
    carry = (y, k, done, jnp.eye(n, dtype=y.dtype), jnp.arange(n, dtype=y.dtype), inf)
    carry = jax.lax.while_loop(newton_cond, newton_body, carry)
    carry = jax.lax.while_loop(chord_cond, chord_body, carry)
    return carry[:3]


@partial(jax.custom_jvp, nondiff_argnums=(5,))
def _solve(table, effects, s, guess, ctx, options):
    return _newton(table, effects, s, guess, ctx, options)


@_solve.defjvp
def _solve_jvp(options, primals, tangents):
    """Implicit differentiation: r(q, θ, s) = 0 ⇒ dq = −(∂r/∂q)⁻¹ (∂r/∂θ dθ + ∂r/∂s ds),
    with a plain-jnp 6×6 solve (no LAPACK call, no error on a failed primal).

    ∂r/∂q from the Newton solve's last factorisation (`_newton(..., factorization=True)`:
    the Jacobian within ~1e-10 mm of the solution, so the same derivative to ~1e-13
    relative) instead of a Jacobian and an elimination of its own: one copy less of the
    residual's derivative in every differentiated program (fits, their Jacobians, the
    diagnosis), which their tracing and compile time scale with. With a chord phase the
    last factorisation is older (up to 1e-3 of the platform radius away): ∂r/∂q is then
    evaluated at the solution."""
    table, effects, s, guess, ctx = primals
    t_table, t_effects, t_s, _, _ = tangents
    reuse = not options.chord_below
    out = _newton(table, effects, s, guess, ctx, options, _length_residual_once, reuse)
    q = out[0]
    _, dr = jax.jvp(
        lambda t, e, s_: _length_residual_once(t, e, q, s_, ctx),
        (table, effects, s),
        (t_table, t_effects, t_s),
    )
    if reuse:  # ∂r/∂q = ∂r/∂y diag(scale) for the scaled unknown y = q·scale
        LU, perm, scale = out[4:]
        finite = jnp.all(jnp.isfinite(LU))  # a diverged solve: finite, meaningless tangents
        LU = jnp.where(finite, LU, jnp.eye(LU.shape[0], dtype=LU.dtype))
        dq = -lu_solve_small(LU, perm, dr[:, None])[:, 0] / scale
        out = out[:4]
    else:
        Jq = jax.jacfwd(lambda qq: _length_residual_once(table, effects, qq, s, ctx))(q)
        dq = -solve_small(Jq, dr[:, None])[:, 0]
    no_tangent = jax.tree.map(lambda x: np.zeros(np.shape(x), dtype=jax.dtypes.float0), out[1:3])
    return out, (dq, *no_tangent, jnp.zeros_like(out[3]))


def forward_one(
    table: Table,
    effects: Effects,
    s: Float[ArrayLike, "6"],
    guess: Float[ArrayLike, "6"],
    options: ForwardOptions = ForwardOptions(),
    ctx: Context | None = None,
) -> tuple[Float[ArrayLike, "6"], RESULTS, Int[ArrayLike, ""], Float[ArrayLike, ""]]:
    """Pose q (6,) at which the table settles for actuator extensions `s` (6,), mm.

    Returns (pose, result, Newton steps, max |residual| in mm). `result` is a `RESULTS`
    item: `RESULTS.successful`, optimistix's failures (singular Jacobian, step limit,
    divergence, non-finite values) or jaxtable's (`residual_above_tolerance`,
    `non_physical_assembly`); a failed solve returns `guess` as its pose (check `result`).
    Differentiable in (table, effects, s), forward and reverse mode, by implicit
    differentiation. `ctx`: the stop's context (direction, temperature, payload, session;
    default: home).
    """
    ctx = Context() if ctx is None else ctx
    return _solve(table, effects, s, guess, ctx, options)
