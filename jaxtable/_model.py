"""The one model function and the inverse (command) solve built on it, for ONE pose.

    actual joint-to-joint length      L_i(q) = |t + R(q) a_i - b_i|
    what the actuator produces        L_i    = L0_i + s_i + sum_k effect_k,i(q, s, context)

Inverse, forward, sensitivities, fits and the simulator all evaluate `length_residual`.
"""

import jax
import jax.numpy as jnp
from jaxtyping import ArrayLike, Float

from ._context import Context
from ._effects import Effects
from ._kinematics import leg_lengths
from ._table import Table

INVERSE_NEWTON_STEPS = 8


def effect_lengths(
    table: Table,
    effects: Effects,
    pose: Float[ArrayLike, "6"],
    s: Float[ArrayLike, "6"],
    ctx: Context | None = None,
) -> Float[ArrayLike, "6"]:
    """Sum of the extra lengths of all `effects` at one pose, mm. Shape (6,). `ctx`: the
    stop's context (default: the home context, direction +1, 20 °C, no payload, session 0)."""
    ctx = Context() if ctx is None else ctx
    total = jnp.zeros(6)
    for name in sorted(effects):
        total = total + effects[name](table, pose, s, ctx)
    return total


def actuator_length(
    table: Table, effects: Effects, pose: Float[ArrayLike, "6"], s: Float[ArrayLike, "6"], ctx=None
) -> Float[ArrayLike, "6"]:
    """L0_i + s_i + sum of effects: the joint-to-joint length the actuator side produces, mm."""
    return table.zero_lengths + s + effect_lengths(table, effects, pose, s, ctx)


def length_residual(
    table: Table, effects: Effects, pose: Float[ArrayLike, "6"], s: Float[ArrayLike, "6"], ctx=None
) -> Float[ArrayLike, "6"]:
    """|l_i(q)| − (L0_i + s_i + effects): zero when pose and extensions are consistent, mm."""
    return leg_lengths(table, pose) - actuator_length(table, effects, pose, s, ctx)


def inverse_extension(
    table: Table, effects: Effects, pose: Float[ArrayLike, "6"], ctx: Context | None = None
) -> tuple[Float[ArrayLike, "6"], Float[ArrayLike, "6"]]:
    """Actuator extensions s (6,) that put the table at `pose`, and the final residual (6,).

    Explicit when no effect depends on s; otherwise a per-leg Newton iteration (each leg's
    extra length depends on its own s_i only) run for a fixed number of steps.
    """
    L = leg_lengths(table, pose)
    zero = jnp.zeros(6)
    s = L - table.zero_lengths - effect_lengths(table, effects, pose, zero, ctx)
    if any(type(e).depends_on_extension for e in effects.values()):

        def residual(s):
            return length_residual(table, effects, pose, s, ctx)

        def step(_, s):
            r, dr = jax.jvp(residual, (s,), (jnp.ones(6),))
            return s - r / dr

        s = jax.lax.fori_loop(0, INVERSE_NEWTON_STEPS, step, s)
    return s, length_residual(table, effects, pose, s, ctx)
