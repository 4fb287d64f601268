"""Design variables: a design (`Design`: geometry + hardware) and the names of its leaves a study
may vary, with their units and default bounds."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._analysis.tolerances import SOURCES
from .._errors import TableFileError
from .._jit import device_array
from .._table import Table, check_table
from .hardware import Hardware
from .symmetric import SymmetricDesign

ANGLES = {
    "base_half_angle",
    "platform_half_angle",
    "base_axis_offset",
    "platform_axis_offset",
    "joint_angle_limit",
    "angular_velocity",
}
"""Variables held in rad and written in degrees in files, the CLI and reports."""

POSITIVE = {
    "base_radius",
    "platform_radius",
    "home_height",
    "lead",
    "stroke",
    "joint_angle_limit",
    "leg_stiffness",
    "efficiency",
    "characteristic_length",
    "inertia",
    "payload",
} | {f"tolerances.{s}" for s in SOURCES}
"""Variables that must stay > 0: their bounds are clipped there and a start below is refused."""

LIMITS = {
    "base_half_angle": (0.0, math.radians(60.0)),
    "platform_half_angle": (0.0, math.radians(60.0)),
    "efficiency": (0.0, 1.0),
}
"""Open intervals a variable must stay in (internal units): a half angle outside (0°, 60°)
makes the legs of a pair cross or swap with the neighbouring pair."""

DISCRETE = ("hand", "lead")
"""Variables enumerated rather than followed by gradient: `hand` (±1 per leg, 2⁶ choices) and
`lead` when a catalogue of leads is given (one lead for all legs)."""


class Design(eqx.Module):
    """A design: `geometry` (a `SymmetricDesign` or a plain `Table`, whose leaves are then the
    variables) and `hardware`. `table()` is the table the criteria see."""

    geometry: SymmetricDesign | Table
    hardware: Hardware

    def table(self) -> Table:
        g = self.geometry
        return g if isinstance(g, Table) else g.table()

    def replace(self, values: dict) -> "Design":
        """This design with the named variables replaced (name -> array, internal units: mm,
        rad, N/mm; names as `--vary` takes them, e.g. `platform_radius`, `lead`,
        `tolerances.SRC`)."""
        return set_values(self, values)

    @staticmethod
    def stack(designs: list["Design"]) -> "Design":
        """Designs stacked leaf by leaf (leading axis n), for `assess_designs` / `jax.vmap`."""
        return stack(designs)


def variable_names(design: Design) -> list[str]:
    """Every name `--vary` accepts for this design."""
    g = design.geometry
    geo = [
        f
        for f in g.__dataclass_fields__
        if f != "name" and not (isinstance(g, Table) and f in ("base_axes", "platform_axes"))
    ]
    hw = [f for f in Hardware.__dataclass_fields__ if f != "tolerances"]
    return geo + hw + [f"tolerances.{s}" for s in SOURCES]


def _getter(design: Design, name: str):
    known = variable_names(design)
    if name not in known:
        kind = "symmetric design" if isinstance(design.geometry, SymmetricDesign) else "table"
        raise ValueError(
            f"unknown design variable '{name}' for a {kind}; known: {', '.join(known)}"
        )
    if name.startswith("tolerances."):
        sub = name.split(".", 1)[1]
        return lambda d: getattr(d.hardware.tolerances, sub)
    if name in Hardware.__dataclass_fields__:
        return lambda d: getattr(d.hardware, name)
    return lambda d: getattr(d.geometry, name)


def get(design: Design, name: str) -> jnp.ndarray:
    """The value of variable `name` (float64 array, internal units)."""
    return jnp.asarray(_getter(design, name)(design), dtype=jnp.float64)


def set_values(design: Design, values: dict) -> Design:
    """`design` with the named variables replaced (name -> array, internal units)."""
    names = list(values)
    getters = [_getter(design, n) for n in names]
    shapes = [jnp.shape(get(design, n)) for n in names]
    new = [
        jnp.broadcast_to(jnp.asarray(values[n], dtype=jnp.float64), s)
        for n, s in zip(names, shapes)
    ]
    return eqx.tree_at(lambda d: [g(d) for g in getters], design, new)


def to_file_units(name: str, value) -> np.ndarray | float:
    """Internal value -> the unit of files and reports (deg for angles)."""
    v = np.asarray(value, dtype=float)
    v = np.rad2deg(v) if name in ANGLES else v
    return float(v) if v.ndim == 0 else v


def unit(name: str) -> str:
    if name in ANGLES:
        return "deg"
    units = {
        "leg_stiffness": "N/mm",
        "payload": "kg",
        "platform_mass": "kg",
        "inertia": "kg·mm²",
        "acceleration": "m/s²",
        "velocity": "mm/s",
        "efficiency": "",
        "lead": "mm/rev",
        "hand": "±1",
    }
    if name.startswith("tolerances."):
        return "mm (budget units)"
    return units.get(name, "mm")


def default_bounds(name: str, value) -> tuple[np.ndarray, np.ndarray]:
    """±50 % of the start (at least ±20° for angles, ±10 mm otherwise), clipped to > 0 for
    positive variables."""
    v = np.asarray(value, dtype=float)
    floor = math.radians(20.0) if name in ANGLES else 10.0
    half = np.maximum(0.5 * np.abs(v), floor if name not in POSITIVE else 0.0)
    half = np.where(half > 0, half, floor)
    lo, hi = v - half, v + half
    if name in POSITIVE:
        lo = np.maximum(lo, 1e-3 * np.abs(v) + 1e-9)
    if name in LIMITS:
        a, b = LIMITS[name]
        pad = 1e-3 * (b - a)
        lo, hi = np.maximum(lo, a + pad), np.minimum(hi, b - pad)
    return np.asarray(lo), np.asarray(hi)


def check_design(design: Design) -> None:
    """Refuse a design outside physical limits, naming the variable: radii, home height > 0;
    leads >= 0; stroke 0 <= lo < hi; hand ±1; then the table checks (`check_table`). The
    hardware checks its own leaves on construction."""
    problems = []
    for name in design.geometry.__dataclass_fields__:
        if name == "name" or name not in POSITIVE | set(LIMITS) | {"hand"}:
            continue
        v = np.asarray(get(design, name))
        if name in LIMITS:
            a, b = LIMITS[name]
            if np.any(~((v > a) & (v < b))):
                problems.append(
                    f"{name} must be in ({to_file_units(name, a):g}, {to_file_units(name, b):g}) "
                    f"{unit(name)}; got {to_file_units(name, v)}"
                )
        elif name == "hand":
            if not np.all(np.isin(v, (-1.0, 1.0))):
                problems.append(f"hand must be ±1 on every leg; got {v.tolist()}")
        elif name == "lead":
            if np.any(v < 0):
                problems.append(f"lead must be >= 0 mm/rev; got {v.tolist()}")
        elif name == "stroke":
            if not (0 <= v[0] < v[1]):
                problems.append(f"stroke must be 0 <= lo < hi (mm); got {v.tolist()}")
        elif np.any(~(v > 0)):
            problems.append(f"{name} must be > 0; got {to_file_units(name, v)} {unit(name)}")
    if problems:
        raise TableFileError("design outside physical limits:\n  " + "\n  ".join(problems))
    check_table(design.table())


def stack(designs: list[Design]) -> Design:
    """Designs stacked leaf by leaf (leading axis), for `jax.vmap` over designs.

    Stacked on the host (numpy) unless a leaf is traced: `jnp.stack` of n device scalars is
    an n-operand concatenation that XLA compiles for every n and leaf shape (1681 designs:
    22 s, against 0.4 s this way)."""

    def leaf(*xs):
        if any(isinstance(x, jax.core.Tracer) for x in xs):
            return jnp.stack(xs)
        return device_array(np.stack([np.asarray(x) for x in xs]))

    return jax.tree.map(leaf, *designs)
