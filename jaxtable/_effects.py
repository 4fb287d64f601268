"""Physical effects: extra leg length added on the actuator side of the model.

An effect is an `eqx.Module` whose `__call__(table, pose, s, ctx)` returns the extra length of
each leg (mm, shape (6,)) for ONE pose `pose` (6,), actuator extensions `s` (6,) (commanded
extension from home, mm) and recording context `ctx` (`Context`: direction of travel,
temperature, payload, session). The extra length of leg i may depend on the pose and on s_i
only (not on the other legs' extensions): the inverse solve relies on that.

The library (DESIGN.md names; `EFFECTS` maps name -> class). Every effect is zero at its
`null` parameters, so geometry + effect nests the geometric model; `typical` is a realistic
magnitude and `prior` the range a fit or a simulation should stay in, each with its source.

| name | extra length | fields |
|---|---|---|
| spiral | hand·lead·Δα_i/(2π) | lead (6,) mm/rev, signed |
| lead_scale | ε_i s_i | eps (6,) |
| backlash | −(w_i/2) d_i | w (6,) mm |
| periodic_lead | a_i sin(2π s_i/p_i) + b_i cos(2π s_i/p_i), p = table lead | a, b (6,) mm |
| thermal | α_i (T − 20 °C) L0_i | alpha (6,) 1/K |
| compliance | F_i(q)/k_i, F = axial force (tension +), static equilibrium | flex = 1/k (6,) mm/N |
| rehoming | c_i,session (first session 0) | offsets (S−1, 6) mm |

`spiral`, `thermal` and `compliance` have a shared form (`shared_fields`): six identical
cylinders share one screw (signed lead: one lead, one hand), one expansion coefficient and
one stiffness, and a fit may tie them (`thermal[all]`, one parameter instead of six). The
other per-leg fields are each cylinder's own: its screw's lead error, periodic error and lost
motion, its homing. `lead_scale`, `backlash` and `periodic_lead` are defects one cylinder can
have alone (`one_leg`: a screw from another batch, a worn nut), so a diagnosis also tests each
of them on one leg (`lead_scale[3]`: leg 3's ε, the other legs' zero).
"""

from collections.abc import Mapping
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._context import REFERENCE_TEMPERATURE, Context
from ._errors import is_concrete
from ._jit import device_array
from ._kinematics import leg_lines, rod_rotation
from ._linalg import solve_small
from ._rotation import rotation_matrix
from ._table import Table, _f64

GRAVITY = 9.80665  # m/s²


def _legs(x) -> Array:
    """One value per leg (6,), float64: a scalar is every leg's (no eager programs where
    concrete: `_table._f64`)."""
    return _f64(x, (6,))


class AbstractEffect(eqx.Module):
    """Base class. Class variables: `name` (the stable string), `fields` (fitted parameter
    fields), `depends_on_extension` (True if the extra length depends on s, so the inverse
    kinematics needs a per-leg Newton solve), `needs` (data the effect needs: "temperature",
    "session", "mass"), `typical` and `prior` (field -> magnitude / (lo, hi), with `source`),
    `shared_fields` (per-leg fields that six identical cylinders share — one material, one
    design — so that a fit may tie them to one number for all legs: the effect's shared form,
    `_params.effect_forms`), `one_leg` (a defect of one cylinder's own parts that it can
    have alone, its other legs' fields zero: the effect's one-leg forms, `_params.leg_forms`)."""

    name: ClassVar[str] = ""
    fields: ClassVar[tuple] = ()
    shared_fields: ClassVar[tuple] = ()
    one_leg: ClassVar[bool] = False
    depends_on_extension: ClassVar[bool] = False
    needs: ClassVar[tuple] = ()
    typical: ClassVar[dict] = {}
    prior: ClassVar[dict] = {}
    source: ClassVar[str] = ""

    def __call__(
        self, table: Table, pose: Float[ArrayLike, "6"], s: Float[ArrayLike, "6"], ctx: Context
    ) -> Float[ArrayLike, "6"]:
        raise NotImplementedError

    @classmethod
    def null(cls, n_sessions: int = 1) -> "AbstractEffect":
        """The effect with zero extra length everywhere (the start of a discovery fit)."""
        return cls()


class Spiral(AbstractEffect):
    """Passive spiral extension: hand·lead·Δα_i(q)/(2π), mm.

    `lead`: (6,) signed lead, mm/rev (positive = right-hand screw, negative = left-hand,
    0 = no passive term on that leg). `Spiral.from_table(table)` takes it from the hardware.
    """

    lead: Float[ArrayLike, "6"]
    name: ClassVar[str] = "spiral"
    fields: ClassVar[tuple] = ("lead",)
    shared_fields: ClassVar[tuple] = ("lead",)  # one screw type
    typical: ClassVar[dict] = {"lead": 12.7}
    prior: ClassVar[dict] = {"lead": (-50.0, 50.0)}
    source: ClassVar[str] = (
        "roller-screw leads 5-20 mm/rev (the paper's cylinders: 12.7 mm, right hand, per the "
        "reference reconstruction); a prior of ±50 mm/rev covers any catalogue screw"
    )

    def __init__(self, lead=0.0):
        self.lead = _legs(lead)

    @classmethod
    def from_table(cls, table: Table) -> "Spiral":
        return cls(table.signed_lead)

    def __call__(self, table, pose, s, ctx=None):
        return self.lead * rod_rotation(table, pose) / (2 * jnp.pi)


class LeadScale(AbstractEffect):
    """Lead (pitch) error proportional to travel: ε_i · s_i, mm. `eps` (6,) dimensionless."""

    eps: Float[ArrayLike, "6"]
    name: ClassVar[str] = "lead_scale"
    one_leg: ClassVar[bool] = True  # one screw or nut
    fields: ClassVar[tuple] = ("eps",)
    depends_on_extension: ClassVar[bool] = True
    typical: ClassVar[dict] = {"eps": 8.3e-5}
    prior: ClassVar[dict] = {"eps": (-5e-4, 5e-4)}
    source: ClassVar[str] = (
        "the paper: 25 µm per 300 mm of travel (8.3e-5); ISO 3408-3 class 7 screws allow "
        "~50 µm/300 mm"
    )

    def __init__(self, eps=0.0):
        self.eps = _legs(eps)

    def __call__(self, table, pose, s, ctx=None):
        return self.eps * s


class Backlash(AbstractEffect):
    """Lost motion: −(w_i/2)·d_i, mm; d_i = +1 if leg i last moved out, −1 if in.
    `w` (6,) mm."""

    w: Float[ArrayLike, "6"]
    name: ClassVar[str] = "backlash"
    one_leg: ClassVar[bool] = True  # one screw or nut
    fields: ClassVar[tuple] = ("w",)
    typical: ClassVar[dict] = {"w": 0.02}
    prior: ClassVar[dict] = {"w": (0.0, 0.2)}
    source: ClassVar[str] = (
        "lost motion of a screw nut, coupling and joint play: 5-30 µm preloaded, up to "
        "0.1-0.2 mm worn; the paper's joint clearance budget is 0.1 mm"
    )

    def __init__(self, w=0.0):
        self.w = _legs(w)

    def __call__(self, table, pose, s, ctx):
        return -0.5 * self.w * ctx.direction


class PeriodicLead(AbstractEffect):
    """Periodic lead error within one screw turn: a_i sin(2π s_i/p_i) + b_i cos(2π s_i/p_i),
    p_i = |lead_i| of the table (a leg with lead 0 has no term). `a`, `b` (6,) mm."""

    a: Float[ArrayLike, "6"]
    b: Float[ArrayLike, "6"]
    name: ClassVar[str] = "periodic_lead"
    one_leg: ClassVar[bool] = True  # one screw or nut
    fields: ClassVar[tuple] = ("a", "b")
    depends_on_extension: ClassVar[bool] = True
    typical: ClassVar[dict] = {"a": 0.005, "b": 0.005}
    prior: ClassVar[dict] = {"a": (-0.05, 0.05), "b": (-0.05, 0.05)}
    source: ClassVar[str] = (
        "ISO 3408-3 travel variation within 2π rad (v_2πp): 6-8 µm for class 3-5 screws"
    )

    def __init__(self, a=0.0, b=0.0):
        self.a = _legs(a)
        self.b = _legs(b)

    def __call__(self, table, pose, s, ctx=None):
        p = jnp.abs(table.lead)
        ok = p > 0
        phase = 2 * jnp.pi * s / jnp.where(ok, p, 1.0)
        return jnp.where(ok, self.a * jnp.sin(phase) + self.b * jnp.cos(phase), 0.0)


class Thermal(AbstractEffect):
    """Thermal growth of the legs: α_i (T − 20 °C) L0_i, mm. `alpha` (6,) 1/K; needs the
    `temperature` column."""

    alpha: Float[ArrayLike, "6"]
    name: ClassVar[str] = "thermal"
    fields: ClassVar[tuple] = ("alpha",)
    shared_fields: ClassVar[tuple] = ("alpha",)  # one material
    needs: ClassVar[tuple] = ("temperature",)
    typical: ClassVar[dict] = {"alpha": 11.5e-6}
    prior: ClassVar[dict] = {"alpha": (-3e-5, 3e-5)}
    source: ClassVar[str] = (
        "steel screws and barrels: 11-12e-6 /K; the controller's model is at 20 °C "
        "(ISO 1 reference temperature)"
    )

    def __init__(self, alpha=0.0):
        self.alpha = _legs(alpha)

    def __call__(self, table, pose, s, ctx):
        return self.alpha * (ctx.temperature - REFERENCE_TEMPERATURE) * table.zero_lengths


def gravity_wrench(table: Table, pose: Float[ArrayLike, "6"], payload=0.0) -> Float[ArrayLike, "6"]:
    """The wrench the legs hold (6,): force N and moment about the platform origin N·mm,
    base axes, of the weight of the platform plus `payload` (kg, at the platform CoG):
    (W, R c × W), W = (0, 0, −m g)."""
    R = rotation_matrix(pose[3:])
    W = jnp.array([0.0, 0.0, -GRAVITY]) * (table.platform_mass + payload)
    return jnp.concatenate([W, jnp.cross(R @ table.platform_cog, W)])


def leg_forces(table: Table, pose: Float[ArrayLike, "6"], payload=0.0) -> Float[ArrayLike, "6"]:
    """Axial leg forces F (6,), N, tension positive, holding the platform mass plus `payload`
    (kg, at the platform CoG) against gravity (−z) in static equilibrium:
    Σ F_i u_i = W and Σ F_i (R a_i × u_i) = R c × W, W = (0, 0, −m g) (`gravity_wrench`)."""
    u, moment = leg_lines(table, pose)
    A = jnp.concatenate([u.T, moment.T], axis=0)  # (6, 6), column i = leg i
    return solve_small(A, gravity_wrench(table, pose, payload)[:, None])[:, 0]


class Compliance(AbstractEffect):
    """Axial leg compliance under the static load: F_i(q)/k_i, mm (compression shortens).
    Stored as `flex` = 1/k (6,) mm/N so that rigid legs are flex = 0; `Compliance.from_k(k)`
    takes k in N/mm. Needs a platform mass (table file) and/or a `payload` column."""

    flex: Float[ArrayLike, "6"]
    name: ClassVar[str] = "compliance"
    fields: ClassVar[tuple] = ("flex",)
    shared_fields: ClassVar[tuple] = ("flex",)  # one cylinder design
    needs: ClassVar[tuple] = ("mass",)
    typical: ClassVar[dict] = {"flex": 1 / 2.0e4}
    prior: ClassVar[dict] = {"flex": (0.0, 1e-3)}
    source: ClassVar[str] = (
        "axial stiffness of a roller-screw cylinder with its bearings and two U-joints: "
        "10-50 N/µm (k = 2e4 N/mm typical, flex 5e-5 mm/N)"
    )

    def __init__(self, flex=0.0):
        self.flex = _legs(flex)

    @classmethod
    def from_k(cls, k) -> "Compliance":
        return cls(1.0 / jnp.asarray(k, dtype=jnp.float64))

    @property
    def k(self):
        return 1.0 / self.flex

    def __call__(self, table, pose, s, ctx):
        return self.flex * leg_forces(table, pose, ctx.payload)


class Rehoming(AbstractEffect):
    """Leg zeros that shift between recording sessions: c_i,session, mm (first session 0).
    `offsets` (S−1, 6): one row per later session. Needs the `session` column."""

    offsets: Float[ArrayLike, "S 6"]
    name: ClassVar[str] = "rehoming"
    fields: ClassVar[tuple] = ("offsets",)
    needs: ClassVar[tuple] = ("session",)
    typical: ClassVar[dict] = {"offsets": 0.03}
    prior: ClassVar[dict] = {"offsets": (-0.5, 0.5)}
    source: ClassVar[str] = "repeatability of a homing switch plus index pulse: 5-50 µm per leg"

    def __init__(self, offsets=np.zeros((0, 6))):
        self.offsets = device_array(offsets, (-1, 6), np.float64)

    @classmethod
    def null(cls, n_sessions: int = 1) -> "Rehoming":
        return cls(np.zeros((max(n_sessions - 1, 0), 6)))

    def __call__(self, table, pose, s, ctx):
        rows = jnp.concatenate([jnp.zeros((1, 6)), self.offsets])
        return rows[jnp.clip(ctx.session, 0, rows.shape[0] - 1)]


EFFECTS: dict[str, type[AbstractEffect]] = {
    c.name: c for c in (Spiral, LeadScale, Backlash, PeriodicLead, Thermal, Compliance, Rehoming)
}


def _shared(x) -> Array:
    return device_array(x, (), np.float64)


class Discovered(AbstractEffect):
    """Terms of the discovery dictionary (DESIGN.md term strings), found in data by
    `diagnose` beyond the library and kept in the model like any effect. Extra length of
    leg i, mm, with s the extensions (mm), d the direction of travel, T = temperature −
    20 °C, t the stop's time over its file (0..1) and k the session index:

    | term | extra length on leg i | per-leg field | shared field | units |
    |---|---|---|---|---|
    | `s^2` | c_i s_i² | s2 (6,) | s2_all | 1/mm |
    | `s^3` | c_i s_i³ | s3 (6,) | s3_all | 1/mm² |
    | `s[j]` | c_ij s_j (j ≠ i: crosstalk) | cross (6, 6) [i, j] | cross_all (6,) [j] | mm/mm |
    | `d*s` | c_i d_i s_i | ds (6,) | ds_all | mm/mm |
    | `T*s` | c_i T s_i | Ts (6,) | Ts_all | 1/K |
    | `t` | c_i t | t (6,) | t_all | mm |
    | `session*s` | c_ki s_i, k ≥ 1 | session_s (S−1, 6) | session_s_all (S−1,) | mm/mm |

    The coefficient on leg i is the per-leg value plus the shared one (a shared term is one
    number for all legs). Every field is zero at `null`. Crosstalk makes leg i depend on the
    other legs' extensions; at the µm/mm level of a real crosstalk the inverse kinematics'
    per-leg Newton still converges (each step shrinks the error by the crosstalk ratio)."""

    s2: Float[ArrayLike, "6"]
    s2_all: Float[ArrayLike, ""]
    s3: Float[ArrayLike, "6"]
    s3_all: Float[ArrayLike, ""]
    cross: Float[ArrayLike, "6 6"]
    cross_all: Float[ArrayLike, "6"]
    ds: Float[ArrayLike, "6"]
    ds_all: Float[ArrayLike, ""]
    Ts: Float[ArrayLike, "6"]
    Ts_all: Float[ArrayLike, ""]
    t: Float[ArrayLike, "6"]
    t_all: Float[ArrayLike, ""]
    session_s: Float[ArrayLike, "S 6"]
    session_s_all: Float[ArrayLike, " S"]
    name: ClassVar[str] = "discovered"
    fields: ClassVar[tuple] = (
        "s2",
        "s2_all",
        "s3",
        "s3_all",
        "cross",
        "cross_all",
        "ds",
        "ds_all",
        "Ts",
        "Ts_all",
        "t",
        "t_all",
        "session_s",
        "session_s_all",
    )
    depends_on_extension: ClassVar[bool] = True
    source: ClassVar[str] = "found in the data (the discovery dictionary), not a library effect"

    def __init__(
        self,
        s2=0.0,
        s2_all=0.0,
        s3=0.0,
        s3_all=0.0,
        cross=np.zeros((6, 6)),
        cross_all=0.0,
        ds=0.0,
        ds_all=0.0,
        Ts=0.0,
        Ts_all=0.0,
        t=0.0,
        t_all=0.0,
        session_s=np.zeros((0, 6)),
        session_s_all=None,
    ):
        self.s2, self.s3, self.ds, self.Ts, self.t = map(_legs, (s2, s3, ds, Ts, t))
        self.s2_all, self.s3_all, self.ds_all, self.Ts_all, self.t_all = map(
            _shared, (s2_all, s3_all, ds_all, Ts_all, t_all)
        )
        xp = np if is_concrete(cross) else jnp  # numpy where concrete: no eager programs
        cross = xp.asarray(cross, dtype=np.float64).reshape(6, 6)
        self.cross = device_array(cross * (1.0 - np.eye(6)))  # no self-crosstalk: lead_scale
        self.cross_all = _legs(cross_all)
        self.session_s = device_array(session_s, (-1, 6), np.float64)
        n = self.session_s.shape[0]
        all_ = np.zeros(n) if session_s_all is None else session_s_all
        self.session_s_all = device_array(all_, (n,), np.float64)

    @classmethod
    def null(cls, n_sessions: int = 1) -> "Discovered":
        k = max(n_sessions - 1, 0)
        return cls(session_s=np.zeros((k, 6)), session_s_all=np.zeros(k))

    def __call__(self, table, pose, s, ctx):
        ctx = Context() if ctx is None else ctx
        others = (self.cross + self.cross_all[None, :]) * (1.0 - jnp.eye(6))
        rows = jnp.concatenate(
            [jnp.zeros((1, 6)), self.session_s + self.session_s_all[:, None]], axis=0
        )
        session = rows[jnp.clip(ctx.session, 0, rows.shape[0] - 1)]
        T = ctx.temperature - REFERENCE_TEMPERATURE
        return (
            (self.s2 + self.s2_all) * s**2
            + (self.s3 + self.s3_all) * s**3
            + others @ s
            + (self.ds + self.ds_all) * ctx.direction * s
            + (self.Ts + self.Ts_all) * T * s
            + (self.t + self.t_all) * ctx.time
            + session * s
        )


# every effect a model (and a model file) may hold: the library and the discovered terms
MODEL_EFFECTS: dict[str, type[AbstractEffect]] = {**EFFECTS, Discovered.name: Discovered}

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
