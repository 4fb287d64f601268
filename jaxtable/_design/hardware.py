"""What a design study needs beyond the table file: the legs' stiffness and drive, the moving
mass, the motion the table must perform, and the tolerance budget (`Hardware`)."""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import ArrayLike, Float

from .._analysis.tolerances import SOURCES, Tolerances
from .._errors import TableFileError, is_concrete
from .._table import Table

DEFAULT_LEG_STIFFNESS = 2.0e4
"""N/mm: a roller-screw cylinder with its bearings and two U-joints (10-50 N/µm; the
`compliance` effect's typical value)."""


def _f64(x) -> jnp.ndarray:
    return jnp.asarray(x, dtype=jnp.float64)


class Hardware(eqx.Module):
    """Design-study inputs that are not in the table file. Every field is a float64 leaf, so
    any of them can be a design variable.

    - `leg_stiffness` (6,): axial stiffness k_i of each leg, N/mm.
    - `payload` (): kg carried at the platform CoG, on top of the table's `platform_mass`.
    - `inertia` (3,): principal moments of inertia of platform + payload about their CoG,
      platform axes, kg·mm².
    - `acceleration` (): m/s², translational, in the worst direction (the leg-force duty).
    - `velocity` (): mm/s, translational, in the worst direction (the motor-speed duty).
    - `angular_velocity` (): rad/s, in the worst direction, added to `velocity`.
    - `efficiency` (): screw and drive efficiency η (torque = F·lead / (2π η)).
    - `characteristic_length` (): mm, scales the rotation columns of the Jacobian so that its
      condition number is dimensionless (dexterity).
    - `tolerances`: the error budget behind the accuracy criteria.

    Build it with `hardware_for(table, ...)`, which fills the defaults that depend on the table.
    """

    leg_stiffness: Float[ArrayLike, "6"]
    payload: Float[ArrayLike, ""]
    inertia: Float[ArrayLike, "3"]
    acceleration: Float[ArrayLike, ""]
    velocity: Float[ArrayLike, ""]
    angular_velocity: Float[ArrayLike, ""]
    efficiency: Float[ArrayLike, ""]
    characteristic_length: Float[ArrayLike, ""]
    tolerances: Tolerances

    def __init__(
        self,
        leg_stiffness,
        payload,
        inertia,
        acceleration,
        velocity,
        angular_velocity,
        efficiency,
        characteristic_length,
        tolerances: Tolerances = Tolerances(),
    ):
        self.leg_stiffness = jnp.broadcast_to(_f64(leg_stiffness), (6,))
        self.payload = _f64(payload)
        self.inertia = jnp.broadcast_to(_f64(inertia), (3,))
        self.acceleration = _f64(acceleration)
        self.velocity = _f64(velocity)
        self.angular_velocity = _f64(angular_velocity)
        self.efficiency = _f64(efficiency)
        self.characteristic_length = _f64(characteristic_length)
        # float64 leaves like the others (a `Tolerances` holds Python floats by default,
        # which a compiled program would take as constants: one program per budget)
        self.tolerances = jax.tree.map(_f64, tolerances)

    def __check_init__(self):
        if not is_concrete(self):
            return
        problems = []
        if not bool(jnp.all(self.leg_stiffness > 0)):
            problems.append("leg_stiffness must be > 0 N/mm on every leg")
        for name in ("payload", "acceleration", "velocity", "angular_velocity"):
            if float(getattr(self, name)) < 0:
                problems.append(f"{name} must be >= 0; got {float(getattr(self, name))}")
        if not bool(jnp.all(self.inertia >= 0)):
            problems.append("inertia must be >= 0 kg·mm²")
        if not 0 < float(self.efficiency) <= 1:
            problems.append(f"efficiency must be in (0, 1]; got {float(self.efficiency)}")
        if not float(self.characteristic_length) > 0:
            problems.append("characteristic_length must be > 0 mm")
        for s in SOURCES:
            if float(getattr(self.tolerances, s)) < 0:
                problems.append(f"tolerances.{s} must be >= 0")
        if problems:
            raise TableFileError("bad design hardware:\n  " + "\n  ".join(problems))

    def moving_mass(self, table: Table) -> Float[ArrayLike, ""]:
        """Platform mass + payload, kg."""
        return table.platform_mass + self.payload


def platform_joint_radius(table: Table) -> Float[ArrayLike, ""]:
    """Mean distance of the platform joints from the platform z axis, mm."""
    return jnp.mean(jnp.linalg.norm(table.platform_joints[:, :2], axis=-1))


def hardware_for(
    table: Table,
    *,
    leg_stiffness=None,
    payload: float = 100.0,
    inertia=None,
    acceleration: float = 5.0,
    velocity: float = 100.0,
    angular_velocity_deg: float = 20.0,
    efficiency: float = 0.9,
    characteristic_length=None,
    tolerances: Tolerances = Tolerances(),
    effects: dict | None = None,
) -> Hardware:
    """`Hardware` with the defaults of a mid-size IMU test table, filled from `table`:

    - leg stiffness: from the model's `compliance` effect (k = 1/flex) when `effects` has one
      with every flex > 0, else 2e4 N/mm;
    - payload 100 kg (IMU and fixture), at the table's platform CoG;
    - inertia: a uniform disc of the platform-joint radius r holding the moving mass m
      (m r²/4, m r²/4, m r²/2);
    - motion: 5 m/s² and 100 mm/s in any direction, plus 20 °/s about any axis; η = 0.9;
    - characteristic length: the platform-joint radius (a rotation of 1 rad then moves a
      platform joint about as far as an r-mm translation);
    - tolerances: the paper's budget.
    """
    r = platform_joint_radius(table)
    if leg_stiffness is None:
        comp = (effects or {}).get("compliance")
        fitted = comp is not None and bool(jnp.all(jnp.asarray(comp.flex) > 0))
        leg_stiffness = 1.0 / comp.flex if fitted else DEFAULT_LEG_STIFFNESS
    m = table.platform_mass + payload
    if inertia is None:
        inertia = jnp.stack([m * r**2 / 4, m * r**2 / 4, m * r**2 / 2])
    return Hardware(
        leg_stiffness=leg_stiffness,
        payload=payload,
        inertia=inertia,
        acceleration=acceleration,
        velocity=velocity,
        angular_velocity=jnp.deg2rad(angular_velocity_deg),
        efficiency=efficiency,
        characteristic_length=r if characteristic_length is None else characteristic_length,
        tolerances=tolerances,
    )
