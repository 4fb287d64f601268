"""Model discovery: fit the geometric model to measured data, test its residuals for structure
beyond the noise, name the responsible effect from the library, extend the model, and measure
the gain on held-out data.

Procedure (`diagnose`):

1. Fit the base model: the 42 geometric parameters (joints modulo the rigid motions the
   instrument frame absorbs, and L0) plus the instrument frame per session and the target,
   through the exact forward kinematics (`_calibrate.fit`).
2. Structure test. Under the model and the stated σ, the weighted residual sum χ² follows a
   χ² law with dof = observations − identifiable parameters. The residuals are "consistent
   with the noise" when P(χ²_dof ≥ χ²) ≥ `alpha` (false-alarm rate `alpha`, default 1 %) AND
   no candidate effect has strong evidence (ΔBIC < −`bic_threshold`): a candidate's
   likelihood-ratio test is a structure test aimed at its own signature, with a false-alarm
   rate far below 1e-6 at that threshold.
3. Candidates. Each applicable library effect not yet in the model is added at its null
   value and fitted with the model (the nested fit); score: ΔBIC = Δχ² + Δrank·ln(n_obs),
   and the k-fold held-out gain 1 − RMS_heldout(model + effect) / RMS_heldout(model) (RMS
   of σ-normalised residuals of rows the fit did not see; `heldout_rms`). The candidate
   with the lowest ΔBIC among those whose held-out gain exceeds `min_gain` and that
   explain at least `min_share` of the excess χ² (χ² − dof) is added; repeat.
4. Stop when the residuals are consistent with the noise or no candidate pays. `unexplained`
   is true when the final model still fails the χ² test: structure remains that no library
   effect explains.

Every fit of one data set, nested model and fold shares one compiled program: all library
effects sit in the model at their null values and the free set and the fitted rows are
traced masks.
"""

import math
import sys
import warnings
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from .. import _params as params
from .._calibration.fit import Calibration, Setup, fit, setup
from .._calibration.heldout import heldout_rms, make_folds
from .._calibration.measurements import Measurements
from .._effects import EFFECTS
from .._table import Table

GEOMETRY = params.GEOMETRY


def _chi2_sf(x: float, dof: int) -> float:
    """P(χ²_dof ≥ x)."""
    if dof <= 0:
        return 1.0
    return float(jax.scipy.special.gammaincc(dof / 2.0, x / 2.0))


def applicable(name: str, nominal: Table, data: Measurements) -> tuple[bool, str]:
    """Whether the data can reveal effect `name` (and why not)."""
    cls = EFFECTS[name]
    if "temperature" in cls.needs:
        if data.temperature is None:
            return False, "no temperature column"
        if np.ptp(np.asarray(data.temperature, float)) < 0.5:
            return False, "temperature varies by less than 0.5 °C"
    if "session" in cls.needs and len(data.sessions) < 2:
        return False, "one session only"
    if "mass" in cls.needs:
        payload = 0.0 if data.payload is None else np.asarray(data.payload, float)
        if float(nominal.platform_mass) <= 0 and not np.any(payload > 0):
            return False, "no platform mass in the table and no payload column"
    if name == "periodic_lead" and not np.any(np.asarray(nominal.lead) > 0):
        return False, "the table has no screw lead (period unknown)"
    return True, ""


@dataclass
class Candidate:
    """Score of one effect added to a model: ΔBIC, k-fold held-out gain and RMS, fitted
    parameters (field -> (value, std) arrays)."""

    effect: str
    delta_bic: float
    heldout_gain: float | None
    heldout_rms: float | None
    chi2: float
    rank: int
    params: dict
    fit: Calibration | None = None
    share: float = 0.0  # share of the model's excess χ² this effect explains

    def as_json(self) -> dict:
        return {
            "effect": self.effect,
            "delta_bic": self.delta_bic,
            "heldout_gain": self.heldout_gain,
            "heldout_rms": self.heldout_rms,
            "excess_chi2_share": self.share,
            "params": {
                k: {"value": v.tolist(), "std": s.tolist()} for k, (v, s) in self.params.items()
            },
        }


@dataclass
class Step:
    """One round of the greedy search: the model it started from, its fit statistics, the
    ranked candidates and the decision."""

    model: list
    chi2: float
    dof: int
    p_value: float
    rms: float
    heldout_rms: float | None
    candidates: list
    decision: str
    added: str | None = None
    fit: Calibration | None = None

    def as_json(self) -> dict:
        return {
            "model": self.model,
            "chi2": self.chi2,
            "dof": self.dof,
            "p_value": self.p_value,
            "rms": self.rms,
            "heldout_rms": self.heldout_rms,
            "candidates": [c.as_json() for c in self.candidates],
            "decision": self.decision,
            "added": self.added,
        }


@dataclass
class Diagnosis:
    """Outcome of `diagnose`. RMS in the same form as `Calibration`: `rms_sigma_before` /
    `rms_sigma_after` (σ-normalised residuals, 1.0 = at the noise; also under their earlier
    names `rms_before` / `rms_after`) and `rms_columns_before` / `rms_columns_after` (per
    measured column, mm / rad); `heldout_rms_*` are σ-normalised."""

    selected: list
    unexplained: bool
    steps: list
    base: Calibration
    final: Calibration
    rms_before: float
    rms_after: float
    heldout_rms_before: float
    heldout_rms_after: float
    not_applicable: dict
    alpha: float
    model_effects: list = field(default_factory=list)  # base + selected: the final model
    noise_mode: str = "fixed"  # "fixed": stated σ; "estimate": σ estimated per model
    setup: Setup = field(repr=False, default=None)
    data: Measurements = field(repr=False, default=None)
    nominal: Table = field(repr=False, default=None)

    @property
    def rms_sigma_before(self) -> float:
        return self.rms_before

    @property
    def rms_sigma_after(self) -> float:
        return self.rms_after

    @property
    def rms_columns_before(self) -> dict:
        return self.base.rms_columns_after

    @property
    def rms_columns_after(self) -> dict:
        return self.final.rms_columns_after

    def fitted_model(self):
        """The final model as a `FittedModel` (table, the effects of the final model, the
        instrument frames per session label and target, the controller's zero lengths):
        what `jaxtable diagnose --out` writes as `calibrated_table.toml`."""
        from .._calibration.model_file import fitted_model

        fm = fitted_model(self.final, self.nominal, self.data.sessions)
        fm.effects = {k: v for k, v in fm.effects.items() if k in self.model_effects}
        return fm

    @property
    def candidates(self) -> list:
        """Candidates of the first step (each effect added to the base model), ranked."""
        return self.steps[0].candidates if self.steps else []

    def effect_params(self, name: str) -> dict:
        """Fitted parameters of a selected effect: field -> (value, std)."""
        return {f: self.final.parameter(f"{name}.{f}") for f in EFFECTS[name].fields}

    def as_json(self) -> dict:
        return {
            "selected": list(self.selected),
            "unexplained": bool(self.unexplained),
            "gain": {
                "rms_before": self.rms_before,
                "rms_after": self.rms_after,
                "heldout_rms_before": self.heldout_rms_before,
                "heldout_rms_after": self.heldout_rms_after,
                "units": "RMS of residuals / sigma (1.0 = instrument noise)",
                "rms_columns_before": self.rms_columns_before,
                "rms_columns_after": self.rms_columns_after,
            },
            "candidates": [c.as_json() for c in self.candidates],
            "steps": [s.as_json() for s in self.steps],
            "not_applicable": self.not_applicable,
            "false_alarm_rate": self.alpha,
            "noise": {
                "mode": self.noise_mode,
                "structure_test": "chi2 against the stated sigma"
                if self.noise_mode == "fixed"
                else "not run: no stated sigma (the candidates' dBIC tests decide)",
                "groups": None if self.final.noise is None else self.final.noise.as_json(),
            },
            "selected_params": {
                name: {f: {"value": v.tolist(), "std": s.tolist()} for f, (v, s) in p.items()}
                for name, p in ((n, self.effect_params(n)) for n in self.selected)
            },
        }


def _norm_rms(cal: Calibration, rows: np.ndarray, mask: np.ndarray) -> float:
    r = cal.residual[rows][mask[rows]]
    return float(np.sqrt(np.mean(r**2)))


def diagnose(
    nominal: Table | Measurements,  # (data, table): the deprecated order
    data: Measurements | Table,
    *,
    base: tuple = (),
    library=None,
    compensated: bool | None = None,
    alpha: float = 0.01,
    bic_threshold: float = 10.0,
    min_gain: float = 0.01,
    min_share: float = 0.3,
    folds: int = 5,
    max_effects: int = 3,
    seed: int = 0,
    log=None,
    noise: str | None = None,
    sigma: dict | None = None,
) -> Diagnosis:
    """Find which library effects the data need beyond the geometric model.

    `nominal`: the table the controller believes; `data`: measurements (all rows are used;
    held-out scores by `folds`-fold cross-validation); `base`: effects in the starting
    model besides the geometry (default none: the rigid model, so even the passive spiral term
    must be found); `library`: candidate effect names (default all of `EFFECTS`);
    `compensated`: without cmd_l columns, whether the controller compensated the spiral term
    (must be stated then, when the table has a lead: the same rule as
    `calibrate`); `alpha`: false-alarm rate of the χ² structure test; `bic_threshold`:
    ΔBIC a candidate must beat; `min_gain`: fractional held-out RMS gain it must bring;
    `min_share`: share of the current excess χ² (χ² − dof) it must explain — an effect that
    only nibbles at a larger unexplained structure is not named as its cause;
    `log`: callable for progress lines (default: stderr); `noise`: "fixed" (the stated σ:
    the χ² structure test runs) or "estimate" (σ estimated for each model in turn; the χ²
    test then has nothing to test against and `unexplained` is never claimed); default:
    "fixed" when the data state σ for every measured cell, else "estimate"; `sigma`:
    {column: σ (mm / rad)} stated by the user (overrides the file's σ columns).
    """
    if isinstance(nominal, Measurements) and isinstance(data, Table):
        warnings.warn(
            "diagnose(data, table) is deprecated: call diagnose(table, data) (model first)",
            DeprecationWarning,
            stacklevel=2,
        )
        nominal, data = data, nominal
    log = log or (lambda msg: print(msg, file=sys.stderr))
    library = list(EFFECTS) if library is None else list(library)
    for name in list(base) + library:
        if name not in EFFECTS:
            raise ValueError(f"unknown effect '{name}'; known: {', '.join(EFFECTS)}")
    n_sessions = len(data.sessions)
    effects = {name: cls.null(n_sessions) for name, cls in EFFECTS.items()}
    free_all = GEOMETRY + tuple(f for name in EFFECTS for f in params.effect_parameters(name))
    st = setup(nominal, data, free_all, effects=effects, compensated=compensated, sigma=sigma)
    mask = st.mask
    all_rows = np.arange(len(data))
    fold_rows = make_folds(len(data), folds, seed)
    not_applicable = {}
    for name in library:
        ok, why = applicable(name, nominal, data)
        if not ok:
            not_applicable[name] = why
    pool = [n for n in library if n not in not_applicable and n not in base]

    def free_mask(model):
        return st.free_mask(GEOMETRY + tuple(f for n in model for f in params.effect_parameters(n)))

    if noise is None:
        noise = "fixed" if st.noise is not None and st.noise.stated.all() else "estimate"
    stated = noise == "fixed"

    def fit_model(model, theta0=None):
        """The current model, with the noise re-estimated for it unless σ is stated."""
        return fit(st, free_mask(model), noise=noise, theta0=theta0)

    model = list(base)
    log(f"fitting the base model ({', '.join(['geometry'] + model)}) on {len(data)} rows ...")
    current = fit_model(model)
    base_fit = current
    steps = []
    while True:
        # candidates are scored with the current model's weights (stated σ, or the σ
        # estimated for the current model), so their χ² compare with its χ²
        p = _chi2_sf(current.chi2, current.dof) if stated else float("nan")
        rms = _norm_rms(current, all_rows, mask)
        log(
            f"model {['geometry'] + model}: chi2/dof = {current.chi2:.1f}/{current.dof}"
            f" (p = {p:.3g}), RMS = {rms:.3f} sigma"
        )
        cands = []
        for name in pool:
            if name in model:
                continue
            cal = fit(st, free_mask(model + [name]), noise="fixed", weight=current.weight)
            dbic = (cal.chi2 - current.chi2) + (cal.rank - current.rank) * math.log(cal.n_obs)
            fitted = {f: cal.parameter(f"{name}.{f}") for f in EFFECTS[name].fields}
            cands.append(Candidate(name, float(dbic), None, None, cal.chi2, cal.rank, fitted, cal))
        cands.sort(key=lambda c: c.delta_bic)
        strong = [c for c in cands if c.delta_bic < -bic_threshold]
        heldout_current = heldout_rms(current, fold_rows, mask)
        for c in cands:
            c.heldout_rms = heldout_rms(c.fit, fold_rows, mask)
            c.heldout_gain = 1.0 - c.heldout_rms / heldout_current
        excess = max(current.chi2 - current.dof, 3.0 * math.sqrt(2.0 * max(current.dof, 1)))
        for c in cands:
            c.share = (current.chi2 - c.chi2) / excess
        for c in cands:
            log(
                f"  candidate {c.effect:14s} dBIC = {c.delta_bic:10.1f}  held-out gain "
                f"{100 * c.heldout_gain:+6.1f} %  explains {100 * c.share:5.0f} % of the excess"
            )
        paying = [c for c in strong if c.heldout_gain > min_gain and c.share >= min_share]
        # without stated σ the χ² test has nothing to test against: only the candidates'
        # likelihood-ratio (ΔBIC) tests decide
        consistent = (p >= alpha or not stated) and not strong
        step = Step(
            ["geometry"] + model,
            current.chi2,
            current.dof,
            p,
            rms,
            heldout_current,
            cands,
            "",
            fit=current,
        )
        steps.append(step)
        if consistent:
            step.decision = "residuals consistent with the noise: stop"
            break
        if not paying:
            step.decision = "structure remains but no candidate pays on held-out data: stop"
            break
        if len(model) - len(base) >= max_effects:
            step.decision = f"reached max_effects = {max_effects}: stop"
            break
        best = paying[0]
        step.added = best.effect
        step.decision = f"add {best.effect}"
        log(f"  -> add {best.effect}")
        model.append(best.effect)
        current = best.fit if stated else fit_model(model, theta0=best.fit.theta)
        heldout_current = best.heldout_rms
    final = current
    heldout_current = heldout_rms(final, fold_rows, mask)
    # before/after in the same units: the final model's σ (stated, or estimated for it)
    to_final = np.where(mask, final.weight / np.where(mask, base_fit.weight, 1.0), 0.0)
    heldout_before = heldout_rms(base_fit, fold_rows, mask, rescale=to_final)
    p_final = _chi2_sf(final.chi2, final.dof) if stated else float("nan")
    return Diagnosis(
        selected=[m for m in model if m not in base],
        model_effects=list(model),
        noise_mode=noise,
        unexplained=bool(stated and p_final < alpha),
        steps=steps,
        base=base_fit,
        final=final,
        rms_before=float(np.sqrt(np.mean((base_fit.residual * to_final)[mask] ** 2))),
        rms_after=_norm_rms(final, all_rows, mask),
        heldout_rms_before=heldout_before,
        heldout_rms_after=heldout_current,
        not_applicable=not_applicable,
        alpha=alpha,
        setup=st,
        data=data,
        nominal=nominal,
    )


# --- signatures: leg-space views of the residuals (for the report) --------------------------


def leg_residuals(diag: Diagnosis, cal: Calibration) -> np.ndarray | None:
    """(N, 6) leg-length equivalent of the pose residuals (mm): δL = (∂L/∂q) δq at the
    fitted pose, with δq the measured-minus-model pose rotated back from the instrument
    frame. Needs all six columns measured (a 6-D tracker); None otherwise."""
    from .._forward import forward_one
    from .._kinematics import leg_lengths
    from .._rotation import rotation_matrix

    st = diag.setup
    if not st.mask.all():
        return None
    problem = st.problem
    sigma = np.where(st.mask, 1.0 / np.asarray(problem.weight), 0.0)
    dq = -cal.residual * sigma  # measured − model
    frame = cal.frame[np.asarray(problem.session)]
    RF = np.asarray(jax.vmap(rotation_matrix)(jnp.asarray(frame[:, 3:])))
    dq[:, :3] = np.einsum("nji,nj->ni", RF, dq[:, :3])
    table, effects = cal.table, cal.effects

    def one(s, g, c, d):
        q = forward_one(table, effects, s, g, ctx=c)[0]
        J = jax.jacfwd(lambda qq: leg_lengths(table, qq))(q)
        return J @ d

    return np.asarray(jax.vmap(one)(problem.s, problem.guess, problem.ctx, jnp.asarray(dq)))


def signatures(diag: Diagnosis) -> dict:
    """Per-leg signature variables (N, 6) the effects respond to: extension s (mm), rod
    rotation Δα (deg), direction d, screw phase 2π s/p (rad), temperature (°C), leg force
    (N), session index."""
    from .._api import rod_rotation
    from .._effects import leg_forces

    st, data, nominal = diag.setup, diag.data, diag.nominal
    problem = st.problem
    s = np.asarray(problem.s)
    n = len(s)
    ctx = problem.ctx
    forces = np.asarray(
        jax.vmap(lambda q, m: leg_forces(nominal, q, m))(jnp.asarray(data.cmd_pose), ctx.payload)
    )
    lead = np.abs(np.asarray(nominal.lead))
    return {
        "extension s (mm)": s,
        "rod rotation (deg)": np.rad2deg(np.asarray(rod_rotation(nominal, data.cmd_pose))),
        "direction of travel": np.asarray(ctx.direction),
        "screw phase (rad)": np.mod(2 * np.pi * s / np.where(lead > 0, lead, np.inf), 2 * np.pi),
        "temperature (°C)": np.repeat(np.asarray(ctx.temperature)[:, None], 6, 1),
        "leg force (N)": forces,
        "session": np.repeat(np.asarray(ctx.session)[:, None], 6, 1).astype(float),
        "row": np.repeat(np.arange(n)[:, None], 6, 1).astype(float),
    }


SIGNATURE_OF = {
    "spiral": "rod rotation (deg)",
    "lead_scale": "extension s (mm)",
    "backlash": "direction of travel",
    "periodic_lead": "screw phase (rad)",
    "thermal": "temperature (°C)",
    "compliance": "leg force (N)",
    "rehoming": "session",
}
