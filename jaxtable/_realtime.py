"""The single-pose actuator command for a real-time controller loop.

The paper's controller computes the compensated command Δl* = Δl − Δl2 every servo cycle.
`command_function` compiles that one-pose map once (the same `inverse_extension` the batch
APIs use, with the table and effects baked in as constants) and returns a callable whose
per-call cost is a few microseconds of dispatch: no pytree flattening of the table, no
re-validation of the model, numpy in and numpy out.
"""

import jax
import jax.numpy as jnp
import numpy as np

from ._context import Context
from ._effects import Effects, resolve_effects
from ._errors import KinematicsError, renamed_argument, require_x64
from ._kinematics import in_stroke
from ._model import inverse_extension
from ._table import Table


class CommandFunction:
    """`f(pose) -> command`: pose (6,) mm / rad -> joint-to-joint command lengths (6,) mm
    (numpy float64), compiled for one table, effect set and context. Make it with
    `command_function`.

    Checks per call: the pose has shape (6,) and is finite, and with `check=True` every
    command lies inside the stroke (evaluated inside the compiled call, returned as one flag);
    otherwise KinematicsError (a controller should hold its last command on error). The
    returned array is a fresh (6,) view of the call's output.
    """

    def __init__(self, table: Table, effects: Effects, context: Context, check: bool):
        require_x64()

        def one(pose):
            s, _ = inverse_extension(table, effects, pose, context)
            cmd = table.zero_lengths + s
            # one flag computed with the command, so a call costs a single scalar test:
            # 1 = non-finite pose, 2 = a command outside the stroke
            bad = jnp.where(
                jnp.all(jnp.isfinite(pose)),
                jnp.where(check & ~jnp.all(in_stroke(table, cmd)), 2.0, 0.0),
                1.0,
            )
            return jnp.concatenate([cmd, bad[None]])

        spec = jax.ShapeDtypeStruct((6,), jnp.float64)
        self._compiled = jax.jit(one).lower(spec).compile()
        self._lo, self._hi = (float(v) for v in np.asarray(table.stroke))

    def __call__(self, pose) -> np.ndarray:
        q = np.asarray(pose, dtype=np.float64)
        if q.shape != (6,):
            raise ValueError(f"pose must have shape (6,), got {q.shape}")
        out = np.asarray(self._compiled(q))
        if out[6] != 0.0:
            self._raise(q, out)
        return out[:6]

    def _raise(self, q, out):
        if out[6] == 1.0:
            raise KinematicsError(f"non-finite pose {q.tolist()}")
        cmd = out[:6]
        bad = np.flatnonzero((cmd < self._lo) | (cmd > self._hi))
        raise KinematicsError(
            f"commanded leg length(s) outside the stroke [{self._lo}, {self._hi}] mm at pose "
            f"{q.tolist()}: " + ", ".join(f"leg {k + 1} {cmd[k]:.3f} mm" for k in bad)
        )


def command_function(
    table: Table,
    *,
    compensated: bool = True,
    compensate: bool | None = None,
    effects: Effects | None = None,
    context: Context | None = None,
    check: bool = True,
) -> CommandFunction:
    """Compile the single-pose command for a real-time loop; see `CommandFunction`.

    Same result as `actuator_command(table, pose, compensated, effects=..., context=...)` for
    one pose (default effects: the table's hardware effects, i.e. the passive spiral term),
    at a fraction of the per-call cost. Compiling takes about a second; do it before the
    loop starts. `context`: one fixed stop context (default home: 20 °C, no payload).
    """
    compensated = renamed_argument(
        compensated, compensate, "compensate", "compensated", "command_function"
    )
    eff = resolve_effects(table, effects) if compensated else {}
    return CommandFunction(table, eff, Context() if context is None else context, check)
