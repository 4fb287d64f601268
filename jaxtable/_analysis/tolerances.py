"""Tolerance budgets: error sources with their standard deviations, propagated to pose error
linearly (covariance through the autodiff sensitivities) and by Monte Carlo through the exact
forward kinematics.

A source is a set of model parameters that share one σ:

| source            | parameter            | σ                                            |
|-------------------|----------------------|----------------------------------------------|
| `base_joints`     | b_i (18)             | `base_joints` mm, each coordinate            |
| `platform_joints` | a_i^p (18)           | `platform_joints` mm, each coordinate        |
| `zero_length`     | L0_i (6)             | `zero_length` mm                             |
| `lead_error`      | lead_scale.eps (6)   | `lead_error` mm per 300 mm of travel / 300   |
| `clearance`       | leg offset ±w/2 (6)  | w/2, w = `clearance` mm (sign unknown)       |
| `spiral_lead`     | spiral.lead (6)      | `spiral_lead` mm/rev (lead the compensation uses) |

Pose errors are reported as translation (mm) and the small rotation vector (rad, base frame),
so a rotation error is an angle whatever the attitude.
"""

from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._effects import LeadScale, Spiral
from .._io import read_toml

SOURCES = (
    "base_joints",
    "platform_joints",
    "zero_length",
    "lead_error",
    "clearance",
    "spiral_lead",
)
PARAMETER = {
    "base_joints": "base_joints",
    "platform_joints": "platform_joints",
    "zero_length": "zero_lengths",
    "lead_error": "lead_scale.eps",
    "clearance": "zero_lengths",
    "spiral_lead": "spiral.lead",
}
UNITS = {
    "base_joints": "mm (σ of each coordinate)",
    "platform_joints": "mm (σ of each coordinate)",
    "zero_length": "mm (σ)",
    "lead_error": "mm per 300 mm of travel (σ)",
    "clearance": "mm (screw-nut clearance w; lost motion ±w/2)",
    "spiral_lead": "mm/rev (σ of the lead used to compensate)",
}


class ToleranceFileError(ValueError):
    """A tolerance file has an unknown source, a negative or non-numeric σ, or bad TOML."""


class Tolerances(eqx.Module):
    """σ of each error source, in the units of `UNITS` (file values). Default: the paper's
    error budget (sec. 2.3): joints machined and assembled within 10 µm, lead error
    25 µm / 300 mm, screw-nut clearance up to 100 µm; L0 10 µm (the paper folds control
    errors into it but gives no figure); spiral lead 0.1 % of 12.7 mm."""

    base_joints: float = 0.010
    platform_joints: float = 0.010
    zero_length: float = 0.010
    lead_error: float = 0.025
    clearance: float = 0.100
    spiral_lead: float = 0.0127

    @property
    def sources(self) -> tuple[str, ...]:
        """The error sources, in the order every budget reports them."""
        return SOURCES

    def sigma(self, source: str):
        """σ of the source's parameter in model units (traceable: a design study may vary
        the tolerances)."""
        v = getattr(self, source)
        if source == "lead_error":
            return v / 300.0
        if source == "clearance":
            return v / 2.0
        return v

    def sigmas(self) -> tuple:
        """σ of every source's parameter in model units (`sigma`), ordered as `SOURCES`."""
        return tuple(self.sigma(s) for s in SOURCES)

    def scaled(self, factor: float) -> "Tolerances":
        return Tolerances(**{s: getattr(self, s) * factor for s in SOURCES})

    def as_dict(self) -> dict:
        return {s: float(getattr(self, s)) for s in SOURCES}


def tolerances_from_dict(doc: dict, where: str = "tolerances") -> Tolerances:
    unknown = [k for k in doc if k not in SOURCES]
    if unknown:
        raise ToleranceFileError(
            f"{where}: unknown error source(s) {', '.join(map(repr, unknown))}; known: "
            f"{', '.join(SOURCES)}"
        )
    values = {}
    for k, v in doc.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            raise ToleranceFileError(f"{where}: '{k}' must be a finite number; got {v!r}")
        if v < 0:
            raise ToleranceFileError(f"{where}: '{k}' must be >= 0 (a σ); got {v}")
        values[k] = float(v)
    return Tolerances(**values)


def load_tolerances(path) -> Tolerances:
    """Read a tolerance file: TOML with any of the keys of `SOURCES` (missing = default)."""
    return tolerances_from_dict(read_toml(path, ToleranceFileError, "tolerance"), str(path))


def save_tolerances(tol: Tolerances, path) -> None:
    lines = ["# jaxtable tolerance budget: one σ per error source"]
    lines += [f"{s} = {getattr(tol, s)!r}  # {UNITS[s]}" for s in SOURCES]
    Path(path).write_text("\n".join(lines) + "\n")


def parameter_sigma(tol: Tolerances) -> dict:
    """{model parameter: σ of each of its elements} the budget gives the table as built
    (model units): joint coordinates, zero lengths (the zero-length σ and the ±w/2
    clearance offset together, as `sample_hardware` draws a leg's length offset: their
    variances add), the lead-scale error and the spiral lead. Used as the prior of a
    calibration (`calibrate(..., prior=tol)`)."""
    return {
        "base_joints": tol.sigma("base_joints"),
        "platform_joints": tol.sigma("platform_joints"),
        "zero_lengths": float(np.hypot(tol.sigma("zero_length"), tol.sigma("clearance"))),
        "lead_scale.eps": tol.sigma("lead_error"),
        "spiral.lead": tol.sigma("spiral_lead"),
    }


def budget_effects(table) -> dict:
    """The effects the propagation differentiates: the hardware spiral term and a zero
    lead-scale error (its derivative is the lead-error sensitivity)."""
    return {"spiral": Spiral.from_table(table), "lead_scale": LeadScale(0.0)}


def sample_hardware(table, tol: Tolerances, n: int, key):
    """`n` hardware realisations drawn from the tolerances: (tables, effects) pytrees with a
    leading sample axis. Joints, L0, lead scale and spiral lead are normal; the clearance is
    ±w/2 with a random sign per leg (the lost motion of an unknown travel direction)."""
    k = jax.random.split(key, 6)
    nrm = jax.random.normal
    dz = tol.sigma("zero_length") * nrm(k[2], (n, 6)) + tol.sigma("clearance") * jnp.where(
        jax.random.bernoulli(k[4], 0.5, (n, 6)), 1.0, -1.0
    )
    tables = eqx.tree_at(
        lambda t: (t.base_joints, t.platform_joints, t.zero_lengths),
        jax.tree.map(lambda x: jnp.broadcast_to(x, (n,) + jnp.shape(x)), table),
        (
            table.base_joints + tol.sigma("base_joints") * nrm(k[0], (n, 6, 3)),
            table.platform_joints + tol.sigma("platform_joints") * nrm(k[1], (n, 6, 3)),
            table.zero_lengths + dz,
        ),
    )
    nominal = budget_effects(table)
    effects = {
        "spiral": eqx.tree_at(
            lambda e: e.lead,
            nominal["spiral"],
            table.signed_lead + tol.sigma("spiral_lead") * nrm(k[5], (n, 6)),
        ),
        "lead_scale": eqx.tree_at(
            lambda e: e.eps, nominal["lead_scale"], tol.sigma("lead_error") * nrm(k[3], (n, 6))
        ),
    }
    return tables, effects
