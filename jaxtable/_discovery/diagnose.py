"""Model discovery: fit the geometric model to measured data, test its residuals for structure
beyond the noise, name the responsible effect from the library, extend the model, and measure
the gain on held-out data.

Procedure (`diagnose`):

1. Fit the base model: the 42 geometric parameters (joints modulo the rigid motions the
   instrument frame absorbs, and L0) plus the instrument frame per session and the target,
   through the exact forward kinematics (`_calibrate.fit`).
2. Structure test, independent of σ's scale (`structure.structure_test`): residuals of
   stops that are neighbours in leg extension (and direction of travel), time or
   temperature must agree no more than the fit's projection of noise makes them (a Monte
   Carlo null law; false-alarm rate `alpha`, default 1 %, for all families together). The
   residuals are "consistent with the noise" when the test sees no structure AND no
   candidate effect has strong evidence (ΔBIC < −`bic_threshold`): a candidate's
   likelihood-ratio test is a structure test aimed at its own signature. The noise itself
   is estimated for every model (variance-component estimation; a stated σ only sets
   relative weights within its group and is reported against the estimate), so a σ stated
   25 % too small or too large, or not at all, gives the same decisions.
3. Candidates. Each applicable library effect not yet in the model is added at its null
   value and fitted with the model (the nested fit); score: ΔBIC = Δχ² + Δrank·ln(n_obs),
   and the k-fold held-out gain 1 − RMS_heldout(model + effect) / RMS_heldout(model) (RMS
   of σ-normalised residuals of rows the fit did not see; `heldout_rms`). The candidate
   with the lowest ΔBIC among those whose held-out gain exceeds `min_gain` and that
   explain at least `min_share` of the excess χ² (χ² − dof) or leave no structure the
   structure test can see is added; repeat. An effect with a shared form is offered in
   both (`thermal[all]`: one coefficient for all legs); a defect one cylinder can have
   alone (`lead_scale`, `backlash`, `periodic_lead`) also on one leg (`lead_scale[3]`): the
   best leg of each, by the score test on the fit's linearisation, is fitted as a candidate
   when its Δχ² could pay, and later legs join it (`lead_scale[2]` beside `lead_scale[5]`)
   until the per-leg form pays more.
   Beside the library, the discovery dictionary (`dictionary.py`) is screened against the
   same fit: its best term is added instead of the best library effect only when it scores
   `priority` ΔBIC units more (library effects keep priority), beats the dictionary-wide
   threshold and pays on held-out rows; it is then refitted jointly with everything else.
4. Stop when the residuals are consistent with the noise or no candidate pays. `unexplained`
   is true when the final model still fails the structure test: structure remains that no
   library effect explains, with the feature families that show it as hints.

Every fit of one data set, nested model and fold shares one compiled program: all library
effects sit in the model at their null values and the free set and the fitted rows are
traced masks.
"""

import dataclasses
import inspect
import math
import sys
import warnings
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from .. import _params as params
from .._calibration.aliases import ScaleAlias, instrument_scale
from .._calibration.fit import (
    OUTLIERS,
    Calibration,
    Setup,
    fit,
    setup,
    warn_not_physical,
    weighed_by,
    weighted_residual,
)
from .._calibration.heldout import UNDEFINED_WORDS, heldout_rms, heldout_text, make_folds
from .._calibration.measurements import Measurements, require_measured
from .._calibration.noise import SPLIT_ALPHA, part_label, report_unit, screen_groups
from .._calibration.outliers import (
    BLUNDER_WORDS,
    TRIAL_ROUNDS,
    GrossError,
    prescreen,
    repeat_words,
    without,
)
from .._calibration.outliers import screen as screen_gross_errors
from .._calibration.stops import merge_stops
from .._effects import EFFECTS, MODEL_EFFECTS, leg_forces
from .._errors import POSE_COLUMNS
from .._jit import jit
from .._table import Table
from .._threads import one_blas_thread
from .changepoint import (
    DriftSource,
    SessionSplit,
    drift_source,
    split_label,
    split_session,
    step_scan,
)
from .dictionary import TERMS, TermCandidate, candidates, compensation_gain, screen, words
from .gp import ResidualGP, min_rows, residual_gp
from .structure import (
    NEIGHBOURS,
    StructureTest,
    TooFewRowsError,
    enough_rows,
    structure_test,
)

GEOMETRY = params.GEOMETRY


def _chi2_sf(x: float, dof: int) -> float:
    """P(χ²_dof ≥ x)."""
    if dof <= 0:
        return 1.0
    from scipy.special import gammaincc  # numpy: jax's compiles an eager program per call shape

    return float(gammaincc(dof / 2.0, x / 2.0))


def equal_legs_p(per_leg: Calibration, shared: Calibration) -> float:
    """Likelihood-ratio test of six identical cylinders: P(χ²_k ≥ χ²_shared − χ²_per-leg),
    k the rank the per-leg form adds, both fits made with the same weights. Small: the data
    reject one coefficient for all legs."""
    return _chi2_sf(max(shared.chi2 - per_leg.chi2, 0.0), per_leg.rank - shared.rank)


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


def _without_blank_context(data: Measurements, base) -> tuple[Measurements, dict]:
    """`data` without its temperature or payload column where that column has blank cells
    and no effect of the starting model `base` reads it, and {need: why} for the
    candidates that would (thermal, the dictionary's T*s; compliance): a candidate cannot
    be fitted on every row, and a filled-in value would be a guess. Where a `base` effect
    reads the column, `data` is returned as it is (the fit then refuses the blank rows,
    naming them)."""
    used = {n for name in base for n in EFFECTS[name].needs}
    blank = {}
    for need, column in (("temperature", "temperature"), ("mass", "payload")):
        values = getattr(data, column)
        if values is None or need in used:
            continue
        rows = np.flatnonzero(~np.isfinite(np.asarray(values, float))) + 1
        if len(rows):
            shown = ", ".join(str(r) for r in rows[:10]) + (", ..." if len(rows) > 10 else "")
            blank[need] = (
                f"{column} blank in {len(rows)} row(s) ({shown}): fill them or drop those "
                "rows to test it"
            )
            data = dataclasses.replace(data, **{column: None})
    return data, blank


@dataclass
class Candidate:
    """Score of one effect added to a model: ΔBIC, k-fold held-out gain and RMS, fitted
    parameters (field -> (value, std) arrays). `effect` holds the form fitted (`thermal`, or
    `thermal[all]` for one coefficient shared by all legs; the JSON's `effect` is the effect
    name and `form` the form)."""

    effect: str
    delta_bic: float
    heldout_gain: float | None
    heldout_rms: float | None
    chi2: float
    rank: int
    params: dict
    # the candidate's fit; once its step is decided, without its Jacobians
    # (`Calibration.light`): a long search does not hold every candidate's (N·6, P) arrays
    fit: Calibration | None = None
    share: float = 0.0  # share of the model's excess χ² this effect explains
    # p-value of the structure test on this candidate's fit, where the share rule asked for it
    # (the effect is named only if it explains the share or leaves no structure): None if not
    structure_after: float | None = None
    # per-leg form of an effect with a shared form: p-value of the likelihood-ratio test of
    # equal legs (its χ² against the shared form's, `equal_legs_p`); None otherwise
    equal_legs_p: float | None = None

    def as_json(self) -> dict:
        return {
            "effect": params.form_effect(self.effect),
            "form": self.effect,  # the effect, `thermal[all]` (one for all legs), `lead_scale[3]`
            "delta_bic": self.delta_bic,
            "heldout_gain": self.heldout_gain,
            "heldout_rms": self.heldout_rms,
            "excess_chi2_share": self.share,
            "structure_p_after": self.structure_after,
            "equal_legs_p": self.equal_legs_p,
            "params": {
                k: {"value": v.tolist(), "std": s.tolist()} for k, (v, s) in self.params.items()
            },
        }


def _shared_form_of(form: str) -> str | None:
    """The shared form of a per-leg form that has one (`"thermal"` -> `"thermal[all]"`);
    None for a shared form or an effect without one."""
    one_form = params.is_shared(form) or params.leg_of(form) is not None
    forms = () if one_form else params.effect_forms(form)
    return forms[1] if len(forms) > 1 else None


def _lighten(steps: list) -> None:
    """Once the last of `steps` is decided: its candidates' fits, and the fits of the steps
    before it, become their `Calibration.light` records (a search scores ~15 candidates a
    step, each fit holding (N·6, P) Jacobians). The last step's fit stays whole: it may be
    the final model's."""
    for c in steps[-1].candidates:
        if c.fit is not None:
            c.fit = c.fit.light()
    for step in steps[:-1]:
        if step.fit is not None:
            step.fit = step.fit.light()


def estimated_sigma(cal: Calibration | None) -> dict | None:
    """{noise group: σ (mm / rad)} a model was fitted with where σ is estimated for each
    model (None where the stated σ were used as they are). Every model's χ²/dof is ~1 at its
    own σ: this σ is what tells the models of a search apart in physical units."""
    n = None if cal is None else cal.noise
    if n is None or not n.estimated:
        return None
    return {name: float(s) for name, s in zip(n.names, n.sigma)}


def estimated_sigma_words(cal: Calibration | None) -> str:
    """'σ estimated for this model: positions 165 µm = 33× the stated, angles 16.7 arcsec =
    8.3× the stated' (without a stated σ, the σ alone), or '' (the stated σ used as they
    are)."""
    sig = estimated_sigma(cal)
    if not sig:
        return ""
    n, parts = cal.noise, []
    for g, (name, columns) in enumerate(zip(n.names, n.columns)):
        unit, f = report_unit(columns)
        text = f"{name} {sig[name] * f:.3g} {unit}"
        if n.stated[g]:
            text += f" = {sig[name] / n.stated_sigma[g]:.2g}× the stated"
        parts.append(text)
    return "σ estimated for this model: " + ", ".join(parts)


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
    structure: StructureTest | None = None
    chi2_p_value: float = float("nan")  # P(χ²_dof ≥ χ²) under the stated σ (noise="fixed")
    screening: object = None  # the dictionary's Screening of this fit (None: not screened)
    terms: list = field(default_factory=list)  # the TermCandidates it screened

    def noise_sigma(self) -> dict | None:
        """{noise group: σ (mm / rad)} of the step's model (`estimated_sigma`)."""
        return estimated_sigma(self.fit)

    def noise_words(self) -> str:
        return estimated_sigma_words(self.fit)

    @property
    def added_effect(self) -> str | None:
        """The library effect the step added (its name, in whichever form: `added` holds the
        form, e.g. `thermal[all]`); None for a dictionary term or no addition."""
        if not self.added or self.added.startswith("term "):
            return None
        return params.form_effect(self.added)

    def as_json(self) -> dict:
        return {
            "model": self.model,
            "chi2": self.chi2,
            "dof": self.dof,
            "p_value": self.p_value,
            "chi2_p_value": None if math.isnan(self.chi2_p_value) else self.chi2_p_value,
            "structure": None if self.structure is None else self.structure.as_json(),
            "rms": self.rms,
            "heldout_rms": self.heldout_rms,
            "noise_sigma": self.noise_sigma(),
            "candidates": [c.as_json() for c in self.candidates],
            "dictionary": None
            if self.screening is None
            else _screening_json(self.screening, self.terms),
            "decision": self.decision,
            "added": self.added if self.added_effect is None else self.added_effect,
            "added_form": self.added,
        }


@dataclass
class Finding:
    """A dictionary term found in the data: the `candidate` (term, legs), its fitted
    `coefficient` and `std` (the term's units, one per key: one value when shared),
    `delta_bic` (−(Δχ² − k ln n) of its screening: negative = evidence), `heldout_gain`
    (fractional k-fold held-out RMS gain of the joint refit), `words`, and the `rivals` that
    explain the data almost as well (an ambiguous finding)."""

    candidate: TermCandidate
    coefficient: np.ndarray
    std: np.ndarray
    delta_bic: float
    heldout_gain: float
    words: str
    rivals: list = field(default_factory=list)
    rival_coefficients: list = field(default_factory=list)  # linearised, one array each
    # RMS commanded-pose error a controller avoids by compensating with the term
    commanded_pose_gain: dict = field(default_factory=dict)
    plan: str | None = None  # pose-plan file that tells it from its rivals (reports)
    # a drift in time (`t`): the instrument's frame against the legs' zeros
    # (`changepoint.DriftSource`), on the fit before the term
    drift_source: DriftSource | None = None

    def as_json(self) -> dict:
        return {
            "term": self.candidate.term,
            "legs": list(self.candidate.legs),
            "shared": self.candidate.shared,
            "coefficient": [float(v) for v in self.coefficient],
            "std": [float(v) for v in self.std],
            "units": TERMS[self.candidate.family].unit,
            "delta_bic": self.delta_bic,
            "heldout_gain": self.heldout_gain,
            "words": self.words,
            "ambiguous_with": [r.label for r in self.rivals],
            "commanded_pose_gain": self.commanded_pose_gain,
            "plan": self.plan,
            "drift_source": None if self.drift_source is None else self.drift_source.as_json(),
        }


def _name(item) -> str:
    """A member of an ambiguous group by its stable name: the term string or the effect."""
    return item.term if isinstance(item, TermCandidate) else params.form_effect(item)


def group_label(item) -> str:
    """A member of an ambiguous group: a dictionary candidate, or a library effect name."""
    if isinstance(item, TermCandidate):
        return item.label
    return f"{params.form_label(item)} (library effect)"


def _screening_json(scr, terms: list, top: int = 10) -> dict:
    order = np.argsort(-np.where(scr.absorbed, -np.inf, scr.score))[:top]
    return {
        "threshold": scr.threshold,
        "p_value": scr.p_value,
        "top": [
            {
                "candidate": terms[i].label,
                "delta_chi2": float(scr.delta_chi2[i]),
                "score": float(scr.score[i]),
                "kept": float(scr.kept[i]),
            }
            for i in order
            if not scr.absorbed[i]
        ],
    }


def _absorbed_terms(cands: list, scr) -> list:
    """Term strings the model already reproduces: the shared form, or every one-leg form,
    is absorbed."""
    out = []
    for term in dict.fromkeys(c.term for c in cands):
        idx = [i for i, c in enumerate(cands) if c.term == term]
        shared = [i for i in idx if cands[i].shared]
        single = [i for i in idx if not cands[i].shared and len(cands[i].legs) == 1]
        if (shared and scr.absorbed[shared].all()) or (single and scr.absorbed[single].all()):
            out.append(term)
    return out


@dataclass
class InstrumentDrift:
    """The instrument's frame found drifting over time (`drift_source` prefers it to a drift
    of the legs' zeros, and its fit pays on held-out rows): fitted as a nuisance of these
    data, per session and frame DOF (`Calibration.frame_drift`), not put in the model, which
    then neither predicts nor compensates it. `source`: the comparison; `heldout_gain`: the
    fractional fall of the held-out RMS when it was fitted; `fit`: the final fit, whose
    `frame_drift_lines` give the values."""

    source: DriftSource
    heldout_gain: float
    fit: Calibration = field(repr=False)

    def words(self) -> str:
        lines = self.fit.frame_drift_lines()
        return (
            "the instrument drifted: "
            + self.source.words()
            + f"; its frame's drift fitted in place of a drift of the legs (held-out RMS "
            f"{-100 * self.heldout_gain:+.1f} %), not put in the model"
            + ("; " + "; ".join(lines) if lines else "")
        )

    def as_json(self) -> dict:
        changes = self.fit.frame_drift_changes()
        return {
            "drift": {k: c[2] for k, c in changes.items()},
            "std": {k: c[3] for k, c in changes.items()},
            "units": "mm, rad: the frame's change over its session, first row to last",
            "delta_chi2": dict(self.source.chi2),
            "dof": dict(self.source.dof),
            "heldout_gain": self.heldout_gain,
            "words": self.words(),
        }


@dataclass
class Diagnosis:
    """Outcome of `diagnose`. RMS in the same form as `Calibration`: `rms_sigma_before` /
    `rms_sigma_after` (σ-normalised residuals, 1.0 = at the noise; also under their earlier
    names `rms_before` / `rms_after`) and `rms_columns_before` / `rms_columns_after` (per
    measured column, mm / rad); `heldout_rms_*` are σ-normalised."""

    selected: list  # library effect names
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
    # the forms the selected effects were fitted in: the name, or `thermal[all]` for one
    # coefficient shared by all legs (`_params.effect_forms`)
    selected_forms: list = field(default_factory=list)
    noise_mode: str = "estimate"  # "estimate": σ estimated per model; "fixed": stated σ
    structure: StructureTest | None = None  # the final model's structure test
    discovered: list = field(default_factory=list)  # Finding per dictionary term found
    absorbed: list = field(default_factory=list)  # term strings the model reproduces
    ambiguous: list = field(default_factory=list)  # groups of TermCandidate
    # per ambiguous group: {"file", "words", "separates", ...} of its discrimination plan,
    # filled when a report is written (`reports.write_diagnosis_report`)
    plans: list = field(default_factory=list)
    screenings: list = field(default_factory=list, repr=False)  # Screening per round
    discovery_alpha: float = 0.05
    setup: Setup = field(repr=False, default=None)
    data: Measurements = field(repr=False, default=None)
    nominal: Table = field(repr=False, default=None)
    # when structure remains unexplained: the GP residual model of the final fit (`gp.py`),
    # what a flexible model gains on held-out rows and what it depends on (hints)
    residual_model: ResidualGP | None = None
    # readings set aside as gross errors (`outliers.GrossError`, largest first); None: kept
    set_aside: list | None = None
    # rows that repeat an earlier row exactly (a stop logged twice: `outliers.Repeat`), set
    # aside before any fit
    repeated: list = field(default_factory=list)
    # stops read more than once (`stops.Stops`), each fitted once at its readings' mean
    stops: object | None = None
    # sessions split at a step in time (`changepoint.SessionSplit`, in the order found)
    split_sessions: list = field(default_factory=list)
    # where the final model has `lead_scale` on every leg: its common part, which pose data
    # cannot tell from the instrument's length scale (`aliases.ScaleAlias`)
    instrument_scale: ScaleAlias | None = None
    # the instrument's frame found drifting over time and fitted as a nuisance
    # (`InstrumentDrift`), in place of a drift term of the legs; None: not found
    instrument_drift: "InstrumentDrift | None" = None

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

    def per_leg_candidate(self, name: str) -> "Candidate | None":
        """For an effect selected in its shared form: its per-leg form as the last step
        scored it against the final model (`equal_legs_p`, the per-leg values and σ);
        None otherwise."""
        last = self.steps[-1] if self.steps else None
        if last is None or last.fit is not self.final:
            return None
        for c in last.candidates:
            if c.effect == name and c.equal_legs_p is not None:
                return c
        return None

    def effect_params(self, name: str) -> dict:
        """Fitted parameters of a selected effect: field -> (value, std), per leg; one value
        for a field its shared form ties; the legs of its one-leg forms only, in leg order
        (`selected_forms`: `lead_scale[2]`, `lead_scale[5]` -> two values, legs 2 and 5)."""
        return {f: self.final.parameter(f"{name}.{f}") for f in EFFECTS[name].fields}

    def form_params(self, form: str) -> dict:
        """Fitted parameters of one of `selected_forms`: field -> (value, std); one value
        for a shared field or a one-leg form."""
        fields = EFFECTS[params.form_effect(form)].fields
        return dict(zip(fields, map(self.final.parameter, params.effect_parameters(form))))

    def as_json(self) -> dict:
        return {
            "selected": list(self.selected),
            "selected_forms": list(self.selected_forms),
            "discovered": [f.as_json() for f in self.discovered],
            "absorbed": list(self.absorbed),
            "ambiguous": [[_name(c) for c in group] for group in self.ambiguous],
            "ambiguous_detail": [
                {
                    "candidates": [group_label(c) for c in group],
                    **(
                        self.plans[i]
                        if i < len(self.plans)
                        else {"plan": None, "plan_words": None, "separates": None}
                    ),
                }
                for i, group in enumerate(self.ambiguous)
            ],
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
                "groups": None if self.final.noise is None else self.final.noise.as_json(),
            },
            "structure": None if self.structure is None else self.structure.as_json(),
            "sessions_split": [sp.as_json() for sp in self.split_sessions],
            "set_aside": None
            if self.set_aside is None
            else [
                {"row": g.row, "column": g.column, "residual": g.residual, "z": g.z}
                for g in self.set_aside
            ],
            "repeated_rows": [{"row": r.row, "of": r.of} for r in self.repeated],
            "stops_read_more_than_once": None
            if self.stops is None
            else self.stops.as_json(self.final.group_sigma()),
            "residual_model": None
            if self.residual_model is None
            else {
                "heldout_gain": self.residual_model.gain,
                "hints": self.residual_model.hints(),
                "components": dict(list(self.residual_model.components.items())[:8]),
                "noise": self.residual_model.noise,
                "rows": len(self.residual_model.rows),
                "rows_total": self.residual_model.rows_total,
            },
            "instrument_scale": None
            if self.instrument_scale is None
            else self.instrument_scale.as_json(),
            "instrument_drift": None
            if self.instrument_drift is None
            else self.instrument_drift.as_json(),
            "selected_params": {
                name: {f: {"value": v.tolist(), "std": s.tolist()} for f, (v, s) in p.items()}
                for name, p in ((n, self.effect_params(n)) for n in self.selected)
            },
        }


def _forms_of(model: list, base) -> list:
    """The library effect forms a model (a list of forms) selected beyond `base`."""
    return [m for m in model if m not in base and m != "discovered"]


def _effects_of(forms: list) -> list:
    """The effects of a list of forms, each once (`lead_scale[2]`, `lead_scale[5]` ->
    `lead_scale`)."""
    return list(dict.fromkeys(params.form_effect(m) for m in forms))


@dataclass(frozen=True)
class _Keys:
    """A one-leg form as the dictionary's screen takes a candidate: its parameter keys."""

    keys: tuple


def _on_all_legs(model: list, effect: str) -> bool:
    """Whether `model` holds `effect` on every leg (per leg or shared)."""
    return any(params.form_effect(m) == effect and params.leg_of(m) is None for m in model)


def _norm_rms(cal: Calibration, rows: np.ndarray, mask: np.ndarray) -> float:
    r = cal.residual[rows][mask[rows]]
    return float(np.sqrt(np.mean(r**2)))


def discovery_setup(
    nominal: Table,
    data: Measurements,
    *,
    compensated: bool | None = None,
    sigma=None,
    column_ratio: dict | None = None,
) -> Setup:
    """The set-up every discovery fit shares: the geometry, every model effect (the
    dictionary's `discovered` included) at its null value, all of them with θ entries, so
    that nested models and folds are masks of one compiled program. The noise groups'
    parts (columns in sessions) keep fixed σ ratios, `column_ratio` ({group name: (6 S,)},
    default one σ per group): a fit of a model that misses an effect must not take the
    effect's excess in one column for that column's noise (`diagnose` measures the ratios on
    its final model). The instrument frame's drift over time (`setup`'s `frame_drift`) has θ
    entries too, frozen unless a diagnosis finds the instrument drifting."""
    effects = {name: cls.null(len(data.sessions)) for name, cls in MODEL_EFFECTS.items()}
    free_all = GEOMETRY + tuple(
        dict.fromkeys(
            f
            for n in MODEL_EFFECTS
            for form in params.effect_forms(n)
            for f in params.effect_parameters(form)
        )
    )
    ratio = {} if column_ratio is None else column_ratio
    return setup(
        nominal,
        data,
        free_all,
        effects=effects,
        compensated=compensated,
        sigma=sigma,
        column_ratio=ratio,
        frame_drift=True,
    )


def _column_ratios(diag: "Diagnosis") -> dict:
    """{group name: (6 S,) σ of its parts (columns in sessions) relative to the group's}
    for the noise groups whose parts' noise the final model's residuals say differs (robust
    test at `SPLIT_ALPHA`); {} if none."""
    n = diag.final.noise
    if n is None or diag.noise_mode != "estimate":
        return {}
    out = {}
    for g, name in enumerate(n.names):
        if n.equal_p[g] < SPLIT_ALPHA:
            ratio = n.column_scale[g] / n.scale[g]
            out[name] = np.where(np.isfinite(ratio) & (ratio > 0), ratio, 1.0)
    return out


def _column_words(diag: "Diagnosis", ratio: dict) -> str:
    n = diag.final.noise
    parts = []
    for g, name in enumerate(n.names):
        if name in ratio:
            unit, f = report_unit(n.columns[g])
            cols = ", ".join(
                f"{part_label(k, n.sessions)} {n.column_sigma[g, k] * f:.3g}" for k in n._parts(g)
            )
            parts.append(f"{name}: {cols} {unit} (one σ: p = {n.equal_p[g]:.2g})")
    return "; ".join(parts)


@one_blas_thread
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
    draws: int = 1000,
    discover: bool = True,
    discovery_alpha: float = 0.05,
    flexible: bool = True,
    max_terms: int = 3,
    ambiguity: float = 6.0,
    priority: float = 10.0,
    outliers: str = "set_aside",
    session_steps: str = "split",
    _column_ratio: dict | None = None,
) -> Diagnosis:
    """Find which library effects the data need beyond the geometric model.

    `nominal`: the table the controller believes; `data`: measurements (all rows are used;
    held-out scores by `folds`-fold cross-validation); `base`: effects in the starting
    model besides the geometry (default none: the rigid model, so even the passive spiral term
    must be found); `library`: candidate effect names (default all of `EFFECTS`);
    `compensated`: without cmd_l columns, whether the controller compensated the spiral term
    (must be stated then, when the table has a lead: the same rule as
    `calibrate`); `alpha`: false-alarm rate of the structure test; `bic_threshold`:
    ΔBIC a candidate must beat; `min_gain`: fractional held-out RMS gain it must bring;
    `min_share`: share of the current excess χ² (χ² − dof) it must explain unless it leaves
    no structure the structure test sees — an effect that only nibbles at a larger
    unexplained structure is not named as its cause;
    `log`: callable for progress lines (default: stderr); `noise`: "estimate" (default: σ
    estimated for each model in turn; stated σ set relative weights within a group and are
    reported against the estimate) or "fixed" (the stated σ as they are, for ΔBIC and the
    χ² p-value the steps report); the structure test and `unexplained` do not depend on
    σ's scale in either mode; `sigma`: {column: σ (mm / rad)} stated by the user
    (overrides the file's σ columns); `draws`: Monte Carlo draws of the structure test and
    the dictionary threshold.

    After the library, the discovery dictionary (`dictionary.py`; `discover=False` skips
    it): each round screens every term against the current fit, reports those the model
    already reproduces as `absorbed`, adds the strongest one that beats the dictionary-wide
    threshold (false discoveries on noise-only data at rate `discovery_alpha`) and pays on
    held-out rows, and refits everything jointly; up to `max_terms` rounds. Terms whose
    penalised scores are within `ambiguity` of the best are reported with it as one
    ambiguous finding.

    When structure remains that nothing named explains (`unexplained`), a Gaussian-process
    residual model of the final fit (`gp.residual_gp`; `flexible=False` skips it) says what
    a flexible model would gain on held-out rows and what the residuals depend on
    (`residual_model`, its `hints()`).

    `outliers`: "set_aside" (default; the rule `calibrate` follows): unless structure is
    left unexplained (then a gross error cannot be told from it), the final model is
    screened for gross errors (`_calibration.outliers`; refitting it without each one found
    in turn); if any, they are set aside (not measured) and the diagnosis is made again on
    the data without them (`set_aside` names them; their residuals are from the final model
    fitted without them). "keep": every reading is fitted. Where structure is left
    unexplained, readings the screen would set aside are set aside only if the final model
    refitted without them leaves none (a burst of gross errors: a tracker that lost its
    beam for three readings).

    `session_steps`: "split" (default): where structure is left unexplained, the final
    model is scanned for a step in time within a session (`changepoint.step_scan`: the
    instrument or the legs' zeros moved part-way through a recording, at the family-wise
    false-alarm rate `alpha`); a step found makes the rows after it a new session
    ('<session>@<row>': its own instrument frame; the library's rehoming effect can take
    the zeros) and the diagnosis is made again, up to `MAX_SPLITS` times (`split_sessions`
    names each, with the held-out RMS before and after). Where the diagnosis with the
    splits still leaves structure unexplained, the steps did not explain it (a drift is
    not a step), and the diagnosis of the file's sessions stands. "keep": sessions as the
    file has them.

    The parts of a noise group (positions, angles), its columns in each session, share one
    σ in every fit unless the final model of the data without gross errors rejects that
    (`noise.SPLIT_ALPHA`, a robust test: a few gross errors do not trigger it); then the
    diagnosis is made again with each part weighted by the σ the final model found for it,
    relative to the group's (σ estimated; with noise="fixed" the stated σ are used as they
    are). Measured on the final model, not per fit, and only where it leaves no structure
    unexplained: a model that misses an effect would take the effect's excess in one column
    for that column's noise.
    """
    if isinstance(nominal, Measurements) and isinstance(data, Table):
        warnings.warn(
            "diagnose(data, table) is deprecated: call diagnose(table, data) (model first)",
            DeprecationWarning,
            stacklevel=2,
        )
        nominal, data = data, nominal
    log = log or (lambda msg: print(msg, file=sys.stderr))
    require_measured(data)
    measured_rows = int(np.isfinite(np.asarray(data.measured)).any(axis=1).sum())
    if not enough_rows(measured_rows):  # before any fit: structure_test's rule, refused later
        raise TooFewRowsError(
            f"a diagnosis needs more than {NEIGHBOURS + 1} measured stops (its structure test "
            f"compares neighbouring stops); {measured_rows} here"
        )
    if outliers not in OUTLIERS:
        raise ValueError(f"outliers must be one of {OUTLIERS}; got {outliers!r}")
    if session_steps not in SESSION_STEPS:
        raise ValueError(f"session_steps must be one of {SESSION_STEPS}; got {session_steps!r}")
    if _column_ratio is None:  # the call a user makes: the passes below
        kw = {k: v for k, v in locals().items() if k in _DIAGNOSE_KEYWORDS}
        set_aside, ratio, decided, splits, first, aside_before = [], {}, False, [], None, 0
        # rows a logger wrote twice and readings no table could have produced (a tracker
        # that lost its target), before any fit (`outliers.prescreen`)
        repeated = []
        if outliers != "keep":
            data, repeated, pre = prescreen(data)
            if repeated:
                log(repeat_words(repeated))
            if pre:
                set_aside += pre
                log(
                    f"{len(pre)} reading(s) no table could have produced set aside before "
                    f"any fit ({BLUNDER_WORDS}): "
                    + "; ".join(g.words() for g in pre[:5])
                    + ("; ..." if len(pre) > 5 else "")
                )
        # a stop read several times: fitted once, at the mean of its readings
        data, stops = merge_stops(data, screen=outliers != "keep")
        if stops is not None:
            log(stops.words())
            set_aside += stops.set_aside
            if stops.set_aside:
                log(
                    f"{len(stops.set_aside)} reading(s) far from the other readings of their "
                    "stop set aside: " + "; ".join(g.words() for g in stops.set_aside[:5])
                )
        weigh = stops is not None
        for _ in range(5 + MAX_SPLITS):
            diag = diagnose(nominal, data, **{**kw, "outliers": "keep", "_column_ratio": ratio})
            if weigh:  # once, from the first pass's final model, before any screen
                weigh = False
                out = weighed_by(data, stops, diag.setup, diag.final)
                if out is not None:
                    data, stops = out
                    log(
                        "the stops were read a different number of times: "
                        + stops.weight_words()
                        + " — diagnosing again with each stop weighted by its own σ"
                    )
                    continue
            # data snooping needs a model that fits: where structure is left unexplained,
            # only readings whose setting aside leaves none (a burst of gross errors)
            found = [] if outliers == "keep" else _final_gross_errors(diag, diag.unexplained)
            if found:
                set_aside += found
                log(
                    f"{len(found)} reading(s) set aside as gross errors: "
                    + "; ".join(g.words() for g in found[:5])
                    + ("; ..." if len(found) > 5 else "")
                    + " — diagnosing again without them"
                )
                data = without(data, found)
                continue
            # structure left that a step in time within a session explains (the instrument
            # or the legs' zeros moved part-way): a new session from the step
            step = None
            if diag.unexplained and session_steps == "split" and len(splits) < MAX_SPLITS:
                step = step_scan(diag.final, diag.setup, alpha=alpha, draws=draws, seed=seed)
            if step is not None and not step.found:
                log(f"  step in time: {step.words()}")
            if step is not None and step.found:
                label = split_label(data, step)
                log(
                    f"{step.words()} — diagnosing again with rows {step.row}… of session "
                    f"{step.session} as session '{label}'"
                )
                splits.append(SessionSplit(step, label))
                if first is None:
                    first, aside_before = diag, len(set_aside)
                data = split_session(data, step.row - 1, label)
                continue
            if decided:
                break
            # the parts' noise ratios, from the final model of the data without gross
            # errors (not where structure is left unexplained: the residuals' spread by
            # column is then the structure's as much as the noise's)
            decided = True
            ratio = {} if diag.unexplained else _column_ratios(diag)
            if not ratio:
                break
            log(
                "the final model's residuals say the noise differs between columns or sessions: "
                + _column_words(diag, ratio)
                + " — diagnosing again with each weighted by its own σ"
            )
        if splits and diag.unexplained:  # steps that do not explain the structure: none
            log(
                "the sessions split at steps in time leave structure unexplained: not "
                "steps (a drift?); the diagnosis of the file's sessions stands"
            )
            diag, set_aside = first, set_aside[:aside_before]
        elif splits:
            before, after = _split_gain(first, diag, folds, seed)
            diag.split_sessions = [
                dataclasses.replace(sp, heldout_rms_before=before, heldout_rms_after=after)
                for sp in splits
            ]
        diag.stops = diag.final.stops = stops
        if outliers == "keep":
            return diag
        diag.set_aside = sorted(set_aside, key=lambda g: -abs(g.z))
        diag.repeated = repeated
        return diag
    base = params.as_names(base)
    library = list(EFFECTS) if library is None else list(params.as_names(library))
    params.check_distinct(base, "effect")
    params.check_distinct(tuple(library), "effect")
    for name in list(base) + library:
        if name not in EFFECTS:
            raise ValueError(f"unknown effect '{name}'; known: {', '.join(EFFECTS)}")
    data, blank = _without_blank_context(data, base)
    st = discovery_setup(
        nominal, data, compensated=compensated, sigma=sigma, column_ratio=_column_ratio
    )
    mask = st.mask
    all_rows = np.arange(len(data))
    fold_rows = make_folds(len(data), folds, seed, strata=data.session_index)
    block_rows = make_folds(len(data), folds, seed, grouped=True)  # terms: grouped folds
    not_applicable = {}
    for name in library:
        ok, why = applicable(name, nominal, data)
        gap = [blank[n] for n in EFFECTS[name].needs if n in blank]
        if gap:  # a column it reads has blank cells (`_without_blank_context`)
            ok, why = False, gap[0]
        if not ok:
            not_applicable[name] = why
    # every form of every applicable effect: spiral, thermal and compliance also with one
    # coefficient for all six (identical) cylinders; ΔBIC decides between the forms
    pool = [
        form
        for n in library
        if n not in not_applicable and n not in base
        for form in params.effect_forms(n)
    ]
    # and the defects one cylinder can have alone on each leg (`lead_scale[3]`), screened on
    # each step's linearisation: only the best leg of each effect is refitted
    leg_pool = [
        form
        for n in library
        if n not in not_applicable and n not in base
        for form in params.leg_forms(n)
    ]

    index = {k: i for i, k in enumerate(st.names)}
    term_keys: list = []  # parameter keys of the dictionary terms found so far
    drift_keys = [k for k in st.names if k.startswith("frame_drift[")]
    nuisance: list = []  # the instrument frame's drift, once found: freed in every fit
    drifting = None  # (DriftSource, held-out gain) where the instrument was found drifting

    def free_mask(model, keys=None):
        """Geometry, the model's library effects, and the dictionary terms found (`keys`,
        default those found so far): "discovered" frees only its found elements, a one-leg
        form its leg's."""
        forms = [form for form in model if form != "discovered"]
        blocks = tuple(
            f
            for form in forms
            if params.leg_of(form) is None
            for f in params.effect_parameters(form)
        )
        fm = st.free_mask(GEOMETRY + blocks)
        legs = [f for form in forms if params.leg_of(form) for f in params.effect_parameters(form)]
        for k in legs + list(term_keys if keys is None else keys) + nuisance:
            fm[index[k]] = 1.0
        return fm

    def mask_of(keys) -> np.ndarray:  # (P,) 1 on the parameters `keys`
        out = np.zeros(len(st.names))
        out[[index[k] for k in keys]] = 1.0
        return out

    def leg_forms_to_fit(model, cal) -> list:
        """The one-leg forms worth a refit at this step: for each effect the model does not
        hold on all legs, its leg (not yet in) with the largest Δχ² on the fit's
        linearisation (the dictionary's score test, exact for an effect linear in its
        parameters), where that Δχ² reaches half of what ΔBIC asks for (the other half is
        room for the geometry's curvature)."""
        offer = [
            f for f in leg_pool if f not in model and not _on_all_legs(model, params.form_effect(f))
        ]
        if not offer:
            return []
        keys = [params.effect_parameters(f) for f in offer]
        dchi2 = screen(cal, st, [_Keys(k) for k in keys], draws=0).delta_chi2
        out = []
        for effect in _effects_of(offer):
            idx = [i for i, f in enumerate(offer) if params.form_effect(f) == effect]
            best = max(idx, key=lambda i: dchi2[i])
            need = bic_threshold + len(keys[best]) * math.log(cal.n_obs)
            if dchi2[best] > 0.5 * need:
                out.append(offer[best])
        return out

    noise = "estimate" if noise is None else noise
    stated = noise == "fixed"

    def test(cal):
        return structure_test(cal, st, alpha=alpha, draws=draws, seed=seed)

    def explains(c: Candidate) -> bool:
        """Is a paying candidate the cause of what it explains? It explains at least
        `min_share` of the excess χ², or it leaves no structure the structure test can see.
        (With σ estimated the excess is the noise floor 3 √(2 dof): the first clause alone
        would ask every library effect for a fixed Δχ².) An effect that nibbles at a larger
        structure leaves that structure behind and fails both."""
        if c.share >= min_share:
            return True
        after = test(c.fit)
        c.structure_after = after.p_value
        log(
            f"  {c.effect}: below {100 * min_share:.0f} % of the excess; with it in, "
            f"{after.words()}"
        )
        return not after.structure

    def fit_model(model, theta0=None):
        """The current model, with the noise re-estimated for it unless σ is stated."""
        return fit(st, free_mask(model), noise=noise, theta0=theta0)

    model = list(base)
    log(f"fitting the base model ({', '.join(['geometry'] + model)}) on {len(data)} rows ...")
    current = fit_model(model)
    base_fit = current
    steps = []
    found, absorbed, ambiguous, screenings = [], [], [], []
    dict_cands = candidates(st, data) if discover else []
    reach = float(np.max(np.abs(np.asarray(st.problem.s)))) if len(data) else 1.0

    def same_units(cal, ref):  # factors expressing cal's σ-normalised residuals in ref's σ
        return np.where(mask, ref.weight / np.where(mask, cal.weight, 1.0), 0.0)

    while True:
        if steps:  # the last step is decided: its records need no Jacobians
            _lighten(steps)
        # candidates are scored with the current model's weights (stated σ, or the σ
        # estimated for the current model), so their χ² compare with its χ²
        p_chi2 = _chi2_sf(current.chi2, current.dof) if stated else float("nan")
        structure = test(current)
        p = structure.p_value
        rms = _norm_rms(current, all_rows, mask)
        log(
            f"model {['geometry'] + model}: chi2/dof = {current.chi2:.1f}/{current.dof}, "
            f"RMS = {rms:.3f} sigma"
            + (f" ({sw})" if (sw := estimated_sigma_words(current)) else "")
            + f"; {structure.words()}"
        )
        heldout_current = heldout_rms(current, fold_rows, mask)
        cands = []
        for name in pool + leg_forms_to_fit(model, current):
            # a form already in, or a shared form where the per-leg one is in: not a step
            # (a shared form in the model is offered its per-leg form, in its place)
            if name in model or (params.is_shared(name) and params.form_effect(name) in model):
                continue
            cal = fit(
                st,
                free_mask(params.with_form(model, name)),
                noise="fixed",
                weight=current.weight,
            )
            dbic = (cal.chi2 - current.chi2) + (cal.rank - current.rank) * math.log(cal.n_obs)
            effect = params.form_effect(name)
            fitted = dict(
                zip(EFFECTS[effect].fields, map(cal.parameter, params.effect_parameters(name)))
            )
            h = heldout_rms(cal, fold_rows, mask)
            if dbic >= -bic_threshold and _shared_form_of(name) not in model:
                cal = cal.light()  # neither added nor an upgrade: only its record is kept
            gain = 1.0 - h / heldout_current
            cands.append(Candidate(name, float(dbic), gain, h, cal.chi2, cal.rank, fitted, cal))
        cands.sort(key=lambda c: c.delta_bic)
        strong = [c for c in cands if c.delta_bic < -bic_threshold]
        excess = max(current.chi2 - current.dof, 3.0 * math.sqrt(2.0 * max(current.dof, 1)))
        for c in cands:
            c.share = (current.chi2 - c.chi2) / excess
        by_form = {c.effect: c for c in cands}
        upgradable = []  # per-leg forms of a shared form in the model
        for c in cands:  # per-leg forms: do the data reject equal legs?
            shared = _shared_form_of(c.effect)
            if shared is None:
                continue
            if shared in model:
                c.equal_legs_p = equal_legs_p(c.fit, current)
                upgradable.append(c)
            elif shared in by_form:
                c.equal_legs_p = equal_legs_p(c.fit, by_form[shared].fit)
        for c in cands:
            log(
                f"  candidate {c.effect:14s} dBIC = {c.delta_bic:10.1f}  held-out gain "
                f"{heldout_text(100 * c.heldout_gain, '+6.1f', ' %'):>8s}  explains "
                f"{100 * c.share:5.0f} % of the excess"
                + ("" if c.equal_legs_p is None else f"; equal legs p = {c.equal_legs_p:.2g}")
            )
        paying = [c for c in strong if c.heldout_gain > min_gain and explains(c)]
        # a shared form in the model: its per-leg form replaces it where the data reject
        # equal legs at `alpha` (likelihood ratio) and it does not lose on held-out rows,
        # after every effect that pays is in (so the legs' differences are not another
        # effect's signal). ΔBIC would keep a false tie until Δχ² > 5 ln n + 10 (p ~ 1e-6 at
        # 150 stops), and a false tie biases every leg by the spread between them; a false
        # per-leg form costs five parameters' variance and no bias
        upgrades = [c for c in upgradable if c.equal_legs_p < alpha and c.heldout_gain > 0]
        paying += [c for c in sorted(upgrades, key=lambda c: c.equal_legs_p) if c not in paying]

        def room(c) -> bool:  # below `max_effects`, or a form of an effect already in
            full = len(_effects_of(_forms_of(model, base))) >= max_effects
            return not full or params.form_effect(c.effect) in _effects_of(model)

        paying = [c for c in paying if room(c)]
        # the dictionary, screened against the same fit
        scr, term = None, None
        live = [c for c in dict_cands if not set(c.keys) & set(term_keys)]
        if live and len(found) < max_terms:
            scr = screen(
                current, st, live, alpha=discovery_alpha, draws=draws, seed=seed + len(steps)
            )
            screenings.append(scr)
            if not steps:
                absorbed = _absorbed_terms(live, scr)
            b = scr.best()
            if b is not None and scr.score[b] > scr.threshold:
                term = b
            log(
                f"  dictionary: best {live[b].label} score {scr.score[b]:.1f} against the "
                f"threshold {scr.threshold:.1f}"
                if b is not None
                else "  dictionary: every term absorbed"
            )
        consistent = not structure.structure and not strong and not upgrades and term is None
        step = Step(
            ["geometry"] + model + (["instrument drift"] if nuisance else []),
            current.chi2,
            current.dof,
            p,
            rms,
            heldout_current,
            cands,
            "",
            fit=current,
            structure=structure,
            chi2_p_value=p_chi2,
            screening=scr,
            terms=live if scr is not None else [],
        )
        steps.append(step)
        if consistent:
            step.decision = "residuals consistent with the noise: stop"
            break
        lib = paying[0] if paying else None
        if term is not None and lib is None:
            # a library effect with strong evidence that pays on held-out rows, if by less
            # than `min_gain`, keeps its priority over a term the dictionary would add for a
            # gain above zero (a defect on one leg must not be named the crosstalk that
            # half-mimics it for want of 1 % held-out gain)
            lib = next(
                (c for c in strong if c.heldout_gain > 0 and room(c) and explains(c)),
                None,
            )
        trial = None
        if term is not None:
            cand = live[term]
            trial = fit(
                st,
                free_mask(model, term_keys + list(cand.keys)),
                noise=noise,
                theta0=current.theta,
            )
        if term is not None and lib is not None:
            # library effects keep priority: the term goes first only when, against every
            # library form that pays (best ΔBIC first), it explains what the library form
            # leaves (it still beats the threshold on the form's fit) and the form adds
            # nothing once the term is in; the first form that keeps its priority is named,
            # and where neither adds to the other the data cannot tell them apart (reported).
            # Every form, not only the best: a one-leg form that leads by ΔBIC can lose to a
            # term that the effect's per-leg form would not
            for rival in [lib] + [c for c in paying if c is not lib]:
                t_left = screen(rival.fit, st, [cand], draws=0).score[0] > scr.threshold
                both = fit(
                    st,
                    free_mask(params.with_form(model, rival.effect), term_keys + list(cand.keys)),
                    noise="fixed",
                    weight=trial.weight,
                    theta0=trial.theta,
                )
                if rival in upgrades:  # the per-leg form by its own test (equal legs rejected)
                    l_left = equal_legs_p(both, trial) < alpha
                else:
                    l_left = (both.chi2 - trial.chi2) + (both.rank - trial.rank) * math.log(
                        both.n_obs
                    ) < -bic_threshold
                log(
                    f"  library {rival.effect} vs term {cand.label}: the term "
                    f"{'adds' if t_left else 'adds nothing'} to {rival.effect}, "
                    f"{rival.effect} {'adds' if l_left else 'adds nothing'} to the term"
                )
                if not (t_left and not l_left):
                    lib = rival
                    if not t_left and not l_left:
                        ambiguous.append([lib.effect, cand])
                        log(f"     ambiguous: {lib.effect} (library) / {cand.label}")
                    term = None
                    break
        if term is not None and cand.family == "t" and drift_keys and not nuisance:
            # a drift in time: the legs' (a term of the model) or the instrument's frame (a
            # nuisance of these data, not of the table)? Where the data prefer the frame, its
            # drift is fitted in place of the term, if it pays on held-out rows
            source = drift_source(current, st, ambiguity)
            if source.preferred == "instrument frame":
                alt = fit(st, np.maximum(free_mask(model), mask_of(drift_keys)), noise=noise,
                          theta0=current.theta)  # fmt: skip
                h_old = heldout_rms(current, block_rows, mask, rescale=same_units(current, alt))
                gain = 1.0 - heldout_rms(alt, block_rows, mask) / h_old
                log(
                    f"  the drift in time is the instrument's: {source.words()}; its frame's "
                    f"drift fitted in place of {cand.label}: held-out RMS {-100 * gain:+.1f} %"
                )
                if gain > 0:
                    nuisance += drift_keys
                    drifting = (source, float(gain))
                    step.added = "instrument frame drift"
                    step.decision = (
                        "fit the instrument frame's drift over time (a nuisance of these data, "
                        "not put in the model)"
                    )
                    current = alt
                    continue
        if term is not None:
            h_old = heldout_rms(current, block_rows, mask, rescale=same_units(current, trial))
            gain = 1.0 - heldout_rms(trial, block_rows, mask) / h_old
            if gain > 0:
                pick = [trial.names.index(k) for k in cand.keys]
                coef, std = trial.value[pick], trial.std[pick]
                rivals = [
                    live[i]
                    for i in np.argsort(-scr.score)
                    if i != term
                    and not scr.absorbed[i]
                    and live[i].term != cand.term
                    and scr.score[term] - scr.score[i] < ambiguity
                    and scr.score[i] > scr.threshold
                ]
                finding = Finding(
                    cand,
                    coef,
                    std,
                    float(-scr.score[term]),
                    float(gain),
                    words(cand.term, cand.legs, cand.shared, coef, reach)
                    + f"; held-out RMS {-100 * gain:+.1f} %",
                    rivals,
                    [np.asarray(scr.coefficient[live.index(r)]) for r in rivals],
                    compensation_gain(trial, st, data, cand, coef),
                )
                g = finding.commanded_pose_gain
                finding.words += (
                    f"; compensating with it moves the commanded pose by "
                    f"{1e3 * g['translation_rms_mm']:.1f} µm / "
                    f"{g['rotation_rms_arcsec']:.2f}″ RMS"
                )
                if cand.family == "t":  # the legs' drift, or the instrument's?
                    finding.drift_source = drift_source(current, st, ambiguity)
                    if finding.drift_source.words():
                        finding.words += "; " + finding.drift_source.words()
                step.added = f"term {cand.label}"
                step.decision = f"add the term {cand.label}"
                log(f"  -> discovered: {finding.words}")
                if rivals:
                    log(f"     ambiguous with {', '.join(r.label for r in rivals)}")
                    ambiguous.append([cand] + rivals)
                found.append(finding)
                term_keys += list(cand.keys)
                if "discovered" not in model:
                    model.append("discovered")
                current = trial
                continue
            log(
                f"  dictionary: {cand.label} does not pay on held-out rows ({100 * gain:+.1f} %)"
                if math.isfinite(gain)
                else f"  dictionary: {cand.label} cannot be checked on held-out rows: "
                f"{UNDEFINED_WORDS}"
            )
        if lib is None:
            step.decision = (
                "structure remains but no candidate pays on held-out data: stop"
                if paying or strong or term is not None or structure.structure
                else "no candidate pays: stop"
            )
            break
        best = lib
        step.added = best.effect
        if best in upgrades:
            step.decision = (
                f"{best.effect} per leg in place of one for all legs: the legs differ "
                f"(equal legs p = {best.equal_legs_p:.2g})"
            )
            log(f"  -> {step.decision}")
        else:
            step.decision = f"add {best.effect}"
            log(f"  -> add {params.form_label(best.effect)}")
        model = params.with_form(model, best.effect)
        current = best.fit if stated else fit_model(model, theta0=best.fit.theta)
        heldout_current = best.heldout_rms
    _lighten(steps)
    final = current
    for f in found:  # the coefficients of the final, joint fit
        pick = [final.names.index(k) for k in f.candidate.keys]
        f.coefficient, f.std = final.value[pick], final.std[pick]
    heldout_current = heldout_rms(final, fold_rows, mask)
    # before/after in the same units: the final model's σ (stated, or estimated for it)
    to_final = np.where(mask, final.weight / np.where(mask, base_fit.weight, 1.0), 0.0)
    heldout_before = heldout_rms(base_fit, fold_rows, mask, rescale=to_final)
    final_structure = steps[-1].structure if steps[-1].fit is final else test(final)
    residual_model = None
    if final_structure.structure and flexible and len(st.mask) < min_rows(folds):
        log(
            "structure remains that nothing named explains; too few stops for a GP residual "
            f"model ({len(st.mask)}: it needs {min_rows(folds)} for {folds} folds)"
        )
    elif final_structure.structure and flexible:
        log("structure remains that nothing named explains: a GP residual model for hints ...")
        residual_model = residual_gp(final, st, folds=folds, seed=seed)
        log(
            f"  GP residual model{residual_model.scope()}: held-out gain "
            f"{100 * residual_model.gain:+.1f} %; "
            f"strongest: {'; '.join(residual_model.hints()[:3])}"
        )
    warn_not_physical(final)
    return Diagnosis(
        selected=_effects_of(_forms_of(model, base)),
        selected_forms=_forms_of(model, base),
        discovered=found,
        absorbed=absorbed,
        ambiguous=ambiguous,
        screenings=screenings,
        discovery_alpha=discovery_alpha,
        model_effects=_effects_of(model),
        noise_mode=noise,
        structure=final_structure,
        unexplained=final_structure.structure,
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
        residual_model=residual_model,
        instrument_scale=instrument_scale(final, mask, alpha) if "lead_scale" in model else None,
        instrument_drift=None if drifting is None else InstrumentDrift(*drifting, final),
    )


SESSION_STEPS = ("split", "keep")
MAX_SPLITS = 2  # sessions a diagnosis splits at steps in time


def _split_gain(before: "Diagnosis", after: "Diagnosis", k: int, seed: int) -> tuple:
    """Held-out RMS of the final models of the diagnosis before a session split and after
    (σ-normalised in the later model's σ, the later data's folds, the readings both fit)."""
    mask = np.asarray(before.setup.mask) & np.asarray(after.setup.mask)
    folds = make_folds(len(after.data), k, seed, strata=after.data.session_index)
    w0, w1 = np.asarray(before.final.weight), np.asarray(after.final.weight)
    to_after = np.where(mask, w1 / np.where(mask, w0, 1.0), 0.0)
    return (
        heldout_rms(before.final, folds, mask, rescale=to_after),
        heldout_rms(after.final, folds, mask),
    )


# diagnose's keywords, passed on when it diagnoses again (without the gross errors, with
# sessions split, with the noise ratios fixed)
_DIAGNOSE_KEYWORDS = [
    p.name
    for p in inspect.signature(diagnose).parameters.values()
    if p.kind is p.KEYWORD_ONLY and p.name != "outliers"
]


def _final_gross_errors(diag: "Diagnosis", trial: bool = False) -> list:
    """Gross errors of the diagnosis's final model (`outliers.screen`), the largest first:
    found one at a time, the final model refitted without each (zero weight) before the
    next is sought; each with its residual from the last refit (measured − model).
    `trial` (the final model leaves structure): at most `TRIAL_ROUNDS`, and none unless
    the refit without them leaves no structure (the rule of `set_aside_gross_errors`)."""
    st, cal = diag.setup, diag.final
    free = np.array([1.0 if n in cal.names else 0.0 for n in st.names])
    groups = np.asarray(st.noise.groups) if st.noise is not None else np.zeros(st.mask.shape)
    mask = np.array(st.mask, bool)
    weight = np.asarray(st.problem.weight, float).copy()
    cells = []
    for _ in range(TRIAL_ROUNDS if trial else 100):
        new, _, _, _ = screen_gross_errors(
            cal,
            mask,
            screen_groups(groups, st.problem.session, st.layout.n_sessions, mask),
            st.problem.s,
            st.problem.session,
        )
        if new is None:
            break
        r, c, _ = new
        cells.append(new)
        mask[r, c] = False
        weight[r, c] = 0.0
        cal = fit(st, free, weight=weight, noise=diag.noise_mode)
    if not cells:
        return []
    if trial:
        law = diag.structure
        if new is not None or structure_test(cal, st, alpha=law.alpha, draws=law.draws).structure:
            return []
    res = weighted_residual(st.problem, st.layout, cal.theta)
    stated = np.asarray(st.problem.weight)
    out = []
    for r, c, z in cells:
        value = -float(res[r, c] / stated[r, c])
        out.append(
            GrossError(r + 1, POSE_COLUMNS[c], value if c < 3 else float(np.rad2deg(value)), z)
        )
    return out


# --- signatures: leg-space views of the residuals (for the report) --------------------------


@jit
def _leg_lengths_jvp(table, poses, dq, frames):
    """(N, 6) (∂L/∂q) δq at each pose (N, 6) for pose changes δq (N, 6) read in instrument
    frames (N, 6): the translation is rotated back to the base frame first."""
    from .._kinematics import leg_lengths
    from .._rotation import rotation_matrix

    def one(q, d, frame):
        d = jnp.concatenate([rotation_matrix(frame[3:]).T @ d[:3], d[3:]])
        return jax.jvp(lambda qq: leg_lengths(table, qq), (q,), (d,))[1]

    return jax.vmap(one)(poses, dq, frames)


@jit
def _leg_forces_batch(table, poses, payloads):
    """(N, 6) poses and (N,) payloads (kg) -> (N, 6) static leg forces (N); one compiled
    program per N. A module-level function rather than `jit(jax.vmap(leg_forces))`, whose
    name would be `leg_forces`'s: the traced-program store keeps only named programs."""
    return jax.vmap(leg_forces, in_axes=(None, 0, 0))(table, poses, payloads)


def leg_residuals(diag: Diagnosis, cal: Calibration) -> np.ndarray | None:
    """(N, 6) leg-length equivalent of the pose residuals (mm): δL = (∂L/∂q) δq, with δq
    the measured-minus-model pose rotated back from the instrument frame and ∂L/∂q of the
    fitted table at the commanded pose (the fitted pose differs from it by at most a few
    tenths of a mm, which changes ∂L/∂q by a relative ~1e-6: far below the residual's own
    precision). Needs all six columns measured (a 6-D tracker); None otherwise."""
    st = diag.setup
    if not st.mask.all():
        return None
    problem = st.problem
    sigma = np.where(st.mask, 1.0 / np.asarray(problem.weight), 0.0)
    dq = -cal.residual * sigma  # measured − model
    frame = cal.frame[np.asarray(problem.session)]
    return np.asarray(_leg_lengths_jvp(cal.table, problem.guess, dq, frame))


def signatures(diag: Diagnosis) -> dict:
    """Per-leg signature variables (N, 6) the effects respond to: extension s (mm), rod
    rotation Δα (deg), direction d, screw phase 2π s/p (rad), temperature (°C), leg force
    (N), session index."""
    from .._api import rod_rotation

    st, data, nominal = diag.setup, diag.data, diag.nominal
    problem = st.problem
    s = np.asarray(problem.s)
    n = len(s)
    ctx = problem.ctx
    forces = np.asarray(_leg_forces_batch(nominal, jnp.asarray(data.cmd_pose), ctx.payload))
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
