"""Physical effects: extra leg length added on the actuator side of the model.

An effect is an `eqx.Module` whose `__call__(table, pose, s)` returns the extra length of each
leg (mm, shape (6,)) for ONE pose `pose` (6,) and actuator extensions `s` (6,) (commanded
extension from home, mm). The extra length of leg i may depend on the pose and on s_i only
(not on the other legs' extensions): the inverse solve relies on that.
"""

from collections.abc import Mapping
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._errors import is_concrete
from ._kinematics import rod_rotation
from ._table import Table


class AbstractEffect(eqx.Module):
    """Base class. Subclasses set `depends_on_extension` (True if the extra length depends on
    s, so the inverse kinematics needs a per-leg Newton solve) and implement `__call__`."""

    depends_on_extension: ClassVar[bool] = False

    def __call__(
        self, table: Table, pose: Float[Array, "6"], s: Float[Array, "6"]
    ) -> Float[Array, "6"]:
        raise NotImplementedError


class Spiral(AbstractEffect):
    """Passive spiral extension: hand·lead·Δα_i(q)/(2π), mm.

    `lead`: (6,) signed lead, mm/rev (positive = right-hand screw, negative = left-hand,
    0 = no passive term on that leg). `Spiral.from_table(table)` takes it from the hardware.
    """

    lead: Float[Array, "6"]

    def __init__(self, lead):
        self.lead = jnp.broadcast_to(jnp.asarray(lead, dtype=jnp.float64), (6,))

    @classmethod
    def from_table(cls, table: Table) -> "Spiral":
        return cls(table.signed_lead)

    def __call__(self, table, pose, s):
        return self.lead * rod_rotation(table, pose) / (2 * jnp.pi)


class LeadScale(AbstractEffect):
    """Lead (pitch) error proportional to travel: ε_i · s_i, mm.

    `eps`: (6,) dimensionless. The paper's roller screws: 25 µm / 300 mm ≈ 8.3e-5.
    """

    eps: Float[Array, "6"]
    depends_on_extension: ClassVar[bool] = True

    def __init__(self, eps=0.0):
        self.eps = jnp.broadcast_to(jnp.asarray(eps, dtype=jnp.float64), (6,))

    def __call__(self, table, pose, s):
        return self.eps * s


Effects = Mapping[str, AbstractEffect]


def default_effects(table: Table) -> dict[str, AbstractEffect]:
    """The effects the hardware has: `spiral` unless every lead is (concretely) zero. A traced
    lead (inside jit/grad) keeps the term, so derivatives with respect to it exist."""
    if is_concrete(table.lead) and not np.any(np.asarray(table.lead) != 0):
        return {}
    return {"spiral": Spiral.from_table(table)}


def resolve_effects(table: Table, effects: Effects | None) -> dict[str, AbstractEffect]:
    """`None` -> the table's hardware effects (`default_effects`); a mapping -> itself
    (`{}` = the rigid geometric model)."""
    if effects is None:
        return default_effects(table)
    for name, eff in effects.items():
        if not isinstance(eff, AbstractEffect):
            raise TypeError(f"effect '{name}' is {type(eff).__name__}, not an AbstractEffect")
    return dict(effects)
