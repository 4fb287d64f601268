"""Model discovery: effects hidden in simulated data (parameters drawn here, at realistic
magnitudes, on tables with random geometric errors: joints σ 10 µm, L0 σ 50 µm, and a 6-D
tracker's noise) must be found, named (as the library effect, never as a dictionary term),
recovered and must pay on held-out data; null data must select nothing; an effect outside the
library must be reported as unexplained when the dictionary is off, and found as its
dictionary term when it is on.

The fast default runs one seed per effect; `pytest -m slow` runs the counts the acceptance
criteria name (5 seeds per effect, 40 null seeds)."""

import dataclasses
import json
import re
from pathlib import Path

import jax
import numpy as np
import pytest
from conftest import quick_jit
from scipy.stats import binom

import jaxtable as jt
from jaxtable import _params as params
from jaxtable._calibration.fit import fit, residual_jit
from jaxtable._calibration.instruments import tracker6
from jaxtable._calibration.measurements import load_measurements, save_measurements
from jaxtable._calibration.simulate import perturb_table, plan_random, simulate
from jaxtable._discovery.diagnose import diagnose, heldout_rms, make_folds
from jaxtable.cli import main

N = 150
EXAMPLE = Path(jt.__path__[0]) / "data" / "example_measurements.csv"


class ExtensionSquared(jt.AbstractEffect):
    """Not in the library: a leg error growing with the square of the extension."""

    g: jax.Array

    def __call__(self, table, pose, s, ctx=None):
        return self.g * s**2


def _nominal():
    return jt.replace(jt.reference_table(), platform_mass=150.0, platform_cog=[0.0, 0.0, 60.0])


def hidden(which: str, rng) -> tuple[dict, dict]:
    """Effects (truth) and extra simulate() arguments for a named case, drawn from rng."""
    kw = {}
    eff = {}
    for name in which.split("+"):
        if name == "spiral":
            eff["spiral"] = jt.Spiral(12.7 * rng.uniform(0.9, 1.1))
        elif name == "lead_scale":
            eff["lead_scale"] = jt.LeadScale(rng.uniform(-1.5e-4, 1.5e-4, 6))
        elif name == "backlash":
            eff["backlash"] = jt.Backlash(rng.uniform(0.01, 0.04, 6))
        elif name == "periodic_lead":
            eff["periodic_lead"] = jt.PeriodicLead(rng.normal(0, 0.005, 6), rng.normal(0, 0.005, 6))
        elif name == "thermal":
            eff["thermal"] = jt.Thermal(11.5e-6 * rng.uniform(0.8, 1.2, 6))
        elif name == "compliance":
            eff["compliance"] = jt.Compliance.from_k(rng.uniform(1.5e4, 3e4, 6))
        elif name == "rehoming":
            eff["rehoming"] = jt.Rehoming(rng.normal(0, 0.03, (1, 6)))
        elif name == "extension_squared":
            eff["extension_squared"] = ExtensionSquared(rng.uniform(1e-6, 3e-6, 6))
        elif name != "null":
            raise ValueError(name)
    # context columns the hardware runs in (present whatever is hidden)
    kw["temperature"] = 20 + 10 * np.arange(N) / N + rng.normal(0, 0.2, N)
    kw["payload"] = rng.choice([0.0, 50.0, 100.0], N)
    if "rehoming" in eff:
        kw["session"] = np.where(np.arange(N) < N // 2, "a", "b")
        kw["frame"] = [[0, 0, 0, 0, 0, 0], [20.0, -10.0, 5.0, 0.01, 0.0, -0.02]]
    return eff, kw


def case(which: str, seed: int):
    rng = np.random.default_rng(1000 + seed)
    nominal = _nominal()
    true = perturb_table(nominal, seed, joint_sigma=0.010, zero_sigma=0.050)
    eff, kw = hidden(which, rng)
    data = simulate(
        nominal,
        true,
        plan_random(N, seed),
        tracker6(),
        effects=eff,
        compensated=False,
        seed=seed,
        **kw,
    )
    return nominal, data, eff


def _quiet(_):
    pass


def _common_value(name, truth, nominal, data):
    """What one coefficient for all legs estimates where the legs' truths differ: their mean
    weighted by how much each leg's regressor x_i (the extra length per unit coefficient,
    DESIGN.md) varies over the stops, Σ_r (x_ir − x̄_i)², the part the leg's zero length
    cannot absorb (least squares of c·x_i on truth_i·x_i, leg by leg)."""
    if np.ptp(truth) == 0:
        return truth[0]
    if name == "compliance":  # F_i(q) / k_i: x = the axial force (static equilibrium)
        # one compiled program (eagerly, each of its ~80 operations compiled on its own)
        forces = quick_jit(jax.vmap(jt.leg_forces, in_axes=(None, 0, 0)))
        x = np.asarray(forces(nominal, np.asarray(data.cmd_pose), np.asarray(data.payload)))
    elif name == "thermal":  # α_i (T − 20) L0_i
        x = (np.asarray(data.temperature) - 20.0)[:, None] * np.asarray(nominal.zero_lengths)
    else:
        raise ValueError(f"no regressor for a shared {name}")
    w = np.sum((x - x.mean(axis=0)) ** 2, axis=0)
    return np.sum(w * truth) / np.sum(w)


def _z_scores(diag, eff, name, nominal, data):
    """(fitted − truth) / std of the effect's parameters in each form it was selected in; a
    field fitted as one number for all legs (its shared form, chosen where the data do not
    reject equal legs) against the legs' common value (`_common_value`), a one-leg form
    against that leg's truth."""
    out = []
    for form in diag.selected_forms:
        if params.form_effect(form) != name:
            continue
        leg = params.leg_of(form)
        for f, (v, s) in diag.form_params(form).items():
            truth = np.asarray(getattr(eff[name], f)).reshape(-1)
            if leg is not None:
                truth = truth[leg - 1 : leg]
            elif v.size == 1 and truth.size > 1:
                truth = _common_value(name, truth, nominal, data)
            out.append((v - truth) / s)
    return np.concatenate(out)


EFFECT_NAMES = [
    "spiral",
    "lead_scale",
    "backlash",
    "periodic_lead",
    "thermal",
    "compliance",
    "rehoming",
]


def _check_single(which, seeds):
    """z-scores of the planted effect's fitted parameters over `seeds`; each diagnosis must
    select it first, leave nothing unexplained and predict held-out rows within 1.3 σ. A
    dictionary term found beside it is a false discovery (the effect is in the library);
    the dictionary's threshold allows those in 5 % of data sets, so over the seeds at most
    the binomial 99 % bound (0 of 1, 2 of 5): "never" would fail a correct method over 5
    seeds of each of the 7 effects 83 % of the time (1 − 0.95³⁵)."""
    z, terms = [], []
    for seed in seeds:
        nominal, data, eff = case(which, seed)
        diag = diagnose(nominal, data, log=_quiet)
        assert diag.selected and diag.selected[0] == which, (seed, diag.selected)
        terms += [(seed, f.candidate.label) for f in diag.discovered]
        assert not diag.unexplained, seed
        assert diag.heldout_rms_after <= 1.3, (seed, diag.heldout_rms_after)
        assert diag.heldout_rms_after < diag.heldout_rms_before
        z.append(_z_scores(diag, eff, which, nominal, data))
    n = len(list(seeds))
    allowed = 0 if n == 1 else binom.ppf(0.99, n, 0.05)
    assert len({s for s, _ in terms}) <= allowed, terms
    z = np.concatenate(z)
    return z


@pytest.mark.parametrize("which", EFFECT_NAMES)
def test_hidden_effect_is_found_and_recovered(which):
    z = _check_single(which, [0])
    assert np.all(np.abs(z) < 4.0), z
    assert np.mean(np.abs(z) < 3.0) >= 5 / 6, z


def test_legs_the_data_tell_apart_replace_a_shared_form():
    """Stiffness drawn per leg (k 1.5–3×10⁴ N/mm): ΔBIC first takes one stiffness for all
    legs; once it is in, the data reject equal legs (likelihood ratio at 1 %), the per-leg
    form replaces it, and no crosstalk term is discovered to carry the legs' differences
    (one was, with every leg off by up to 6.8σ, before the test of equal legs)."""
    nominal, data, eff = case("compliance", 1)
    diag = diagnose(nominal, data, log=_quiet)
    assert [s.added for s in diag.steps[:2]] == ["compliance[all]", "compliance"]
    upgrade = next(c for c in diag.steps[1].candidates if c.effect == "compliance")
    assert upgrade.equal_legs_p < 0.01 and upgrade.heldout_gain > 0
    assert "per leg in place of one for all legs" in diag.steps[1].decision
    assert diag.selected_forms == ["compliance"] and not diag.discovered
    z = _z_scores(diag, eff, "compliance", nominal, data)
    assert z.shape == (6,) and np.all(np.abs(z) < 3.0), z


@pytest.mark.slow
@pytest.mark.parametrize("which", EFFECT_NAMES)
def test_hidden_effect_five_seeds(which):
    z = _check_single(which, range(1, 6))
    assert np.mean(np.abs(z) < 3.0) >= 0.95, z
    assert np.all(np.abs(z) < 4.5), z


@pytest.mark.parametrize("which", ["spiral+backlash", "lead_scale+thermal"])
def test_two_hidden_effects_are_both_selected(which):
    nominal, data, eff = case(which, 7)
    diag = diagnose(nominal, data, log=_quiet)
    assert set(diag.selected) == set(which.split("+")), diag.selected
    assert not diag.unexplained
    assert diag.heldout_rms_after <= 1.3
    # the search keeps the (N·6, P) Jacobians of the final fit only; the records of the
    # fits it scored keep their values, σ and residuals
    assert len(diag.steps) >= 3 and diag.steps[-1].fit is diag.final
    assert diag.final.jacobian is not None and diag.final.jacobian_full is not None
    records = [s.fit for s in diag.steps[:-1]] + [c.fit for s in diag.steps for c in s.candidates]
    assert all(f.jacobian is None and f.jacobian_full is None for f in records)
    assert all(f.redundancy is None and f.residual.shape == (len(data), 6) for f in records)
    first = diag.steps[0].candidates[0]
    effect = first.effect.removesuffix("[all]")
    for k, (value, std) in first.params.items():
        np.testing.assert_array_equal(first.fit.parameter(f"{effect}.{k}")[0], value)
        np.testing.assert_array_equal(first.fit.parameter(f"{effect}.{k}")[1], std)


ONE_LEG = ["lead_scale", "backlash", "periodic_lead"]


def one_leg_case(which: str, seed: int):
    """A defect of one cylinder's screw or nut (a screw from another batch, a worn nut): the
    effect on a drawn leg, at 5-8 σ of its one-leg coefficient — where the six-parameter
    per-leg form mostly misses ΔBIC — and on the other legs at a tenth of its σ (cylinders
    are never exactly alike)."""
    rng = np.random.default_rng(2000 + seed)
    nominal = _nominal()
    true = perturb_table(nominal, seed, joint_sigma=0.010, zero_sigma=0.050)
    leg = int(rng.integers(6))
    v = np.zeros((2, 6))
    if which == "lead_scale":  # σ(ε) ≈ 1.2e-5 here
        v[0] = rng.normal(0, 1.2e-6, 6)
        v[0, leg] = rng.choice([-1, 1]) * rng.uniform(6e-5, 9e-5)
        eff = jt.LeadScale(v[0])
    elif which == "backlash":  # σ(w) ≈ 0.9 µm
        v[0] = np.abs(rng.normal(0, 1e-4, 6))
        v[0, leg] = rng.uniform(0.005, 0.008)
        eff = jt.Backlash(v[0])
    else:  # a sin + b cos of the screw's angle, σ(a), σ(b) ≈ 0.8 µm
        v = rng.normal(0, 1e-4, (2, 6))
        phase = rng.uniform(0, 2 * np.pi)
        v[:, leg] = rng.uniform(0.005, 0.008) * np.array([np.cos(phase), np.sin(phase)])
        eff = jt.PeriodicLead(v[0], v[1])
    kw = {
        "temperature": 20 + 10 * np.arange(N) / N + rng.normal(0, 0.2, N),
        "payload": rng.choice([0.0, 50.0, 100.0], N),
    }
    data = simulate(
        nominal,
        true,
        plan_random(N, seed),
        tracker6(),
        effects={which: eff},
        compensated=False,
        seed=seed,
        **kw,
    )
    return nominal, data, {which: eff}, leg + 1


def _check_one_leg(which, seeds):
    """Each diagnosis names the effect on the planted leg alone, recovers its coefficients
    (z-scores returned) and does not name the dictionary's look-alikes (crosstalk `s[j]` on
    that leg, a direction-dependent scale `d*s`) in its place."""
    z = []
    for seed in seeds:
        nominal, data, eff, leg = one_leg_case(which, seed)
        diag = diagnose(nominal, data, log=_quiet)
        assert diag.selected_forms == [f"{which}[{leg}]"], (seed, leg, diag.selected_forms)
        assert not diag.discovered and not diag.unexplained, (seed, diag.discovered)
        assert diag.heldout_rms_after < diag.heldout_rms_before
        z.append(_z_scores(diag, eff, which, nominal, data))
    return np.concatenate(z)


def test_a_lead_error_on_one_leg_is_named_on_that_leg_not_crosstalk():
    """A lead error on one screw: named `lead_scale[leg]`, ε within 3σ. Before the one-leg
    forms, the per-leg form (six coefficients) missed ΔBIC and the dictionary named leg j's
    extension on that leg (crosstalk, which ε·s_i correlates with)."""
    z = _check_one_leg("lead_scale", [1])
    assert np.all(np.abs(z) < 3.0), z


@pytest.mark.slow
@pytest.mark.parametrize("which", ONE_LEG)
def test_a_defect_on_one_leg_is_named_on_that_leg_five_seeds(which):
    z = _check_one_leg(which, range(2, 7))
    assert np.mean(np.abs(z) < 3.0) >= 0.9 and np.all(np.abs(z) < 4.5), z


def test_lead_errors_on_two_legs_are_named_on_both():
    """Two screws from another batch (legs drawn, ε 6-9e-5 each): both legs named, alone or
    by the per-leg form, and no dictionary term in their place."""
    rng = np.random.default_rng(31)
    nominal = _nominal()
    true = perturb_table(nominal, 31, joint_sigma=0.010, zero_sigma=0.050)
    legs = rng.choice(6, 2, replace=False)
    eps = rng.normal(0, 1.2e-6, 6)
    eps[legs] = rng.choice([-1, 1], 2) * rng.uniform(6e-5, 9e-5, 2)
    data = simulate(
        nominal,
        true,
        plan_random(N, 31),
        tracker6(),
        effects={"lead_scale": jt.LeadScale(eps)},
        compensated=False,
        seed=31,
    )
    diag = diagnose(nominal, data, log=_quiet)
    assert diag.selected == ["lead_scale"] and not diag.discovered, diag.selected_forms
    named = set(map(params.leg_of, diag.selected_forms))
    assert named == {None} or named == set(legs + 1), (legs + 1, diag.selected_forms)
    v, s = diag.effect_params("lead_scale")["eps"]
    truth = eps if named == {None} else eps[np.sort(legs)]
    assert np.all(np.abs((v - truth) / s) < 3.0), (v, truth, s)


def _null_selections(seeds):
    """Per noise-only data set: everything diagnose claims (library effects, dictionary
    terms, "unexplained")."""
    out = []
    for seed in seeds:
        nominal, data, _ = case("null", seed)
        diag = diagnose(nominal, data, log=_quiet)
        out.append(
            diag.selected
            + [f.candidate.label for f in diag.discovered]
            + (["unexplained"] if diag.unexplained else [])
        )
    return out


def test_null_data_select_nothing_20_seeds():
    """Noise-only data, the full pipeline: at most 2 of 20 data sets with any claim. A
    method at the stated ~6 % passes with probability 0.89; one at 33 % with 0.018 (the
    200-data-set rate is `studies/discovery_null.py`)."""
    assert binom.cdf(2, 20, 0.06) > 0.85 and binom.cdf(2, 20, 0.33) < 0.02
    sel = _null_selections(range(100, 120))
    assert sum(bool(s) for s in sel) <= 2, sel


@pytest.mark.slow
def test_null_data_select_nothing_40_seeds():
    """Any claim on noise-only data in at most ~5 % of data sets (the dictionary's rate; the
    structure test adds 1 %): the limit a correct 5 % method exceeds with probability 1 %."""
    sel = _null_selections(range(200, 240))
    assert sum(bool(s) for s in sel) <= binom.ppf(0.99, 40, 0.06), sel


@pytest.mark.parametrize("seed", [0])
def test_effect_outside_the_library_is_unexplained(seed):
    """With the dictionary off, an error growing with extension² is structure nothing in
    the library explains; with it on, it is found as the dictionary's `s^2` per leg."""
    nominal, data, eff = case("extension_squared", seed)
    diag = diagnose(nominal, data, log=_quiet, discover=False)
    assert diag.unexplained, diag.selected
    assert diag.selected == [], diag.selected  # no library name is forced on it
    assert diag.structure.hints[0] in ("extensions", "extensions, direction")
    # the flexible model sees it too: a held-out gain, and extensions as what it depends on
    gp = diag.residual_model
    assert gp is not None and gp.gain > 0.05, gp
    assert "extension" in gp.hints()[0], gp.components
    assert diag.as_json()["residual_model"]["hints"] == gp.hints()
    diag = diagnose(nominal, data, log=_quiet)
    assert diag.selected == [] and not diag.unexplained, diag.selected
    # the per-leg coefficients drawn here are alike (1-3e-6 /mm): the data may describe
    # them by one shared coefficient (then a compromise between them) or per leg
    found = diag.discovered[0]
    assert (found.candidate.term, found.candidate.legs) == ("s^2", (1, 2, 3, 4, 5, 6))
    g = np.asarray(eff["extension_squared"].g)
    if found.candidate.shared:
        assert g.min() < found.coefficient[0] < g.max(), (found.coefficient, g)
    else:
        assert np.all(np.abs(found.coefficient - g) < 3 * found.std), (found.coefficient, g)
    assert diag.heldout_rms_after <= 1.3


@pytest.mark.slow
def test_effect_outside_the_library_six_seeds():
    for seed in range(1, 7):
        nominal, data, _ = case("extension_squared", seed)
        diag = diagnose(nominal, data, log=_quiet, discover=False)
        assert diag.unexplained and diag.selected == [], (seed, diag.selected)


def _misstated(data, factor):
    """The data with σ stated `factor` × the truth (None: no σ columns)."""
    return dataclasses.replace(data, sigma=None if factor is None else data.sigma * factor)


def test_null_data_with_sigma_stated_25_percent_too_small():
    nominal, data, _ = case("null", 104)
    diag = diagnose(nominal, _misstated(data, 0.75), log=_quiet)
    assert diag.selected == [] and not diag.unexplained, diag.selected
    ratio = diag.final.noise.scale[0]  # positions: the data imply σ 1/0.75 × the stated
    lo, hi = diag.final.noise.ratio_interval[0]
    assert lo < 1 / 0.75 < hi and not diag.final.noise.consistent[0], (ratio, lo, hi)


def test_effects_found_without_sigma_columns():
    nominal, data, _ = case("backlash", 11)
    diag = diagnose(nominal, _misstated(data, None), log=_quiet)
    assert diag.selected == ["backlash"] and not diag.unexplained, diag.selected
    words = diag.steps[-1].noise_words()  # no σ stated: the σ alone, no ratio to a statement
    assert words.startswith("σ estimated for this model: positions") and "×" not in words
    nominal, data, _ = case("extension_squared", 11)
    diag = diagnose(nominal, _misstated(data, 1.25), log=_quiet, discover=False)
    assert diag.unexplained and diag.selected == [], diag.selected
    assert diag.structure.hints[0] in ("extensions", "extensions, direction")
    # the flexible model sees it too: a held-out gain, and extensions as what it depends on
    gp = diag.residual_model
    assert gp is not None and gp.gain > 0.05, gp
    assert "extension" in gp.hints()[0], gp.components
    assert diag.as_json()["residual_model"]["hints"] == gp.hints()


def test_blank_context_cells_leave_out_the_candidates_that_read_them():
    """A temperature logger that missed three stops and a payload cell lost: the effects
    that read those columns (thermal, compliance) cannot be fitted on every row, so they
    are not tried (the report says why and which rows), and the rest of the diagnosis is
    made on every row: the hidden spiral term is found. A starting model that reads the
    column refuses the blank rows, naming them."""
    nominal, data, _ = case("spiral", 3)
    temperature, payload = data.temperature.copy(), data.payload.copy()
    temperature[[3, 50, 90]] = np.nan
    payload[7] = np.nan
    gappy = dataclasses.replace(data, temperature=temperature, payload=payload)
    diag = diagnose(nominal, gappy, log=_quiet, discover=False, flexible=False)
    assert diag.selected[0] == "spiral" and not diag.unexplained, diag.selected
    why = diag.not_applicable
    assert why["thermal"].startswith("temperature blank in 3 row(s) (4, 51, 91)"), why
    assert why["compliance"].startswith("payload blank in 1 row(s) (8)"), why
    assert "thermal" not in {c.effect.split("[")[0] for c in diag.candidates}
    assert diag.rms_after < 1.3 and diag.heldout_rms_after < 1.3  # every row fitted
    with pytest.raises(ValueError, match=r"row 4, column 'temperature'.*thermal"):
        diagnose(nominal, gappy, base=("thermal",), log=_quiet, discover=False, flexible=False)


@pytest.mark.slow
def test_misstated_sigma_false_alarms_over_60_data_sets():
    """Noise-only data with σ stated 25 % too small, 25 % too large and not at all (20 seeds
    each): any library effect, dictionary term or `unexplained` counts as a false
    discovery; its rate must not exceed 5 % (upper limit a correct method passes with
    probability 99 %)."""
    false = 0
    for k, factor in enumerate((0.75, 1.25, None)):
        for seed in range(300 + 20 * k, 320 + 20 * k):
            nominal, data, _ = case("null", seed)
            diag = diagnose(nominal, _misstated(data, factor), log=_quiet)
            false += bool(diag.selected or diag.discovered or diag.unexplained)
    assert false <= binom.ppf(0.99, 60, 0.05), false


@pytest.mark.slow
def test_misstated_sigma_keeps_real_effects_six_seeds():
    for seed in range(20, 26):
        factor = (0.75, 1.25, None)[seed % 3]
        nominal, data, eff = case("lead_scale", seed)
        diag = diagnose(nominal, _misstated(data, factor), log=_quiet)
        assert diag.selected[:1] == ["lead_scale"] and not diag.unexplained, (seed, diag.selected)
        nominal, data, _ = case("extension_squared", seed)
        diag = diagnose(nominal, _misstated(data, factor), log=_quiet, discover=False)
        assert diag.unexplained and diag.selected == [], (seed, diag.selected)


def test_heldout_formula_equals_refits():
    nominal, data, eff = case("backlash", 3)
    diag = diagnose(nominal, data, log=_quiet)
    st = diag.setup
    folds = make_folds(len(data), 5, 0)
    for cal in (diag.base, diag.final):
        free = st.free_mask([])  # rebuild the model's mask from its fitted names
        free = np.array([1.0 if n in cal.names else 0.0 for n in st.names])
        sq, count = 0.0, 0
        for rows in folds:
            keep = np.setdiff1d(np.arange(len(data)), rows)
            refit = fit(st, free, keep, noise="fixed", weight=cal.weight)  # the fit's σ
            r = np.asarray(residual_jit(refit.theta, (st.problem, st.layout))).reshape(-1, 6)
            # residual_jit weighs by the stated σ; the fit's σ were estimated
            stated = np.where(st.mask, np.asarray(st.problem.weight), 1.0)
            r = r * np.where(st.mask, cal.weight / stated, 0.0)
            sq += float((r[rows] ** 2).sum())
            count += r[rows].size
        np.testing.assert_allclose(heldout_rms(cal, folds, st.mask), np.sqrt(sq / count), rtol=1e-4)


# --- the bundled example ---------------------------------------------------------------------


def example_data():
    """The bundled example: the reference table (random geometric errors) measured by a 6-D
    tracker set up 1.2 m away, 150 random stops, an uncompensated controller; hidden: the
    passive spiral term of the hardware's screws and backlash."""
    nominal = jt.reference_table()
    rng = np.random.default_rng(2014)
    true = perturb_table(nominal, 2014, joint_sigma=0.010, zero_sigma=0.050)
    eff = {
        "spiral": jt.Spiral.from_table(nominal),
        "backlash": jt.Backlash(rng.uniform(0.015, 0.035, 6)),
    }
    temperature = np.round(21.0 + 2.0 * np.arange(N) / N + rng.normal(0, 0.1, N), 2)
    return simulate(
        nominal,
        true,
        plan_random(N, 2014),
        tracker6(),
        effects=eff,
        compensated=False,
        frame=[1200.0, -300.0, 150.0, np.deg2rad(0.5), np.deg2rad(-0.3), np.deg2rad(30.0)],
        temperature=temperature,
        seed=2014,
    )


def test_bundled_example_is_reproducible(tmp_path):
    save_measurements(example_data(), tmp_path / "example.csv")
    assert (tmp_path / "example.csv").read_text() == EXAMPLE.read_text()


def test_gross_errors_are_set_aside_and_the_diagnosis_made_without_them(tmp_path, capsys):
    """The bundled example with a broken beam (x +0.8 mm at row 21), a 0.01° pitch glitch
    at row 100 and a beam lost for three readings in a row (y +0.2, +0.3, +0.25 mm at rows
    61–63, which leave structure in time: before, they were kept and the structure left
    unexplained): the command line names the readings with their whole error, the JSON
    lists them, and the diagnosis is the one of the clean file (the same selection, no
    structure left). With --keep-outliers no screen runs (`set_aside` null, where a screen
    that found nothing gives an empty list), shown on the clean file: on this one the kept
    glitches leave structure, and the rediagnosis and residual model that follow took
    half the test's time to show the same flag."""
    data = load_measurements(EXAMPLE)
    m = data.measured.copy()
    m[20, 0] += 0.8
    m[99, 4] += np.deg2rad(0.01)
    m[60:63, 1] += [0.2, 0.3, 0.25]
    path = tmp_path / "glitch.csv"
    save_measurements(dataclasses.replace(data, measured=m), path)
    out = tmp_path / "d"
    assert main(["diagnose", str(path), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "5 reading(s) set aside as gross errors: row 21 x +0.79" in printed, printed
    doc = json.loads((out / "diagnosis.json").read_text())
    planted = {(21, "x"): 0.8, (100, "pitch"): 0.01, (61, "y"): 0.2, (62, "y"): 0.3,
               (63, "y"): 0.25}  # fmt: skip
    found = {(g["row"], g["column"]): g["residual"] for g in doc["set_aside"]}
    assert set(found) == set(planted), found
    for cell, error in planted.items():
        assert abs(found[cell] - error) < 0.2 * error, (cell, found[cell])
    assert doc["selected_forms"] == ["spiral[all]", "backlash"]
    assert doc["unexplained"] is False
    assert "set aside as gross errors" in (out / "report.md").read_text()
    assert main(["diagnose", str(EXAMPLE), "--out", str(out), "--keep-outliers"]) == 0
    assert json.loads((out / "diagnosis.json").read_text())["set_aside"] is None


def test_an_unmodelled_drift_is_structure_not_gross_errors():
    """A thermal drift the geometric model misses leaves readings far out (6.6 robust σ):
    the residuals show structure, so the gross-error screen does not run and says why;
    diagnose left without the thermal effect (an empty library) sets nothing aside either
    (with the screen run regardless, 52 readings of this case were set aside). The GP
    residual model is left off (`flexible=False`): it would take ~15 s of this test's ~18
    to give hints nothing here reads (`test_effect_outside_the_library_is_unexplained`
    checks them on data of this form)."""
    nominal, data, _ = case("thermal", 0)
    cal = jt.calibrate(nominal, data)
    assert cal.set_aside == [] and cal.screen_skipped, cal.set_aside
    assert "gross errors: not screened: the residuals show structure" in cal.report()
    diag = diagnose(nominal, data, log=_quiet, library=[], discover=False, flexible=False)
    assert diag.unexplained and diag.set_aside == []


def test_diagnose_cli_on_the_bundled_example(tmp_path, capsys):
    out = tmp_path / "diag"
    assert main(["diagnose", "--out", str(out), "--json", str(tmp_path / "d.json")]) == 0
    doc = json.loads((tmp_path / "d.json").read_text())
    assert doc["selected"] == ["spiral", "backlash"]
    assert doc["unexplained"] is False
    assert doc["set_aside"] == []  # screened, nothing found (--keep-outliers: null)
    g = doc["gain"]
    assert g["rms_after"] < g["rms_before"] and g["heldout_rms_after"] <= 1.3
    assert {c["effect"] for c in doc["candidates"]} >= {"spiral", "backlash", "thermal"}
    assert "compliance" in doc["not_applicable"]  # no platform mass, no payload
    for c in doc["candidates"]:
        assert {"effect", "delta_bic", "heldout_gain", "params"} <= set(c)
    assert len(doc["steps"]) == 3 and doc["steps"][0]["added"] == "spiral"
    # the example's six cylinders have one screw: the shared form, one lead for all legs
    assert doc["selected_forms"] == ["spiral[all]", "backlash"]
    assert doc["steps"][0]["added_form"] == "spiral[all]"
    assert {c["form"] for c in doc["candidates"]} >= {"spiral", "spiral[all]", "backlash"}
    text = (out / "report.md").read_text()
    assert "spiral" in text and (out / "residual_signatures.png").exists()
    assert (out / "effect_backlash.png").exists()
    # σ is estimated for each model (the file states 5 µm / 2″ and was simulated with them):
    # every step's χ²/dof is ~1, and the σ each model needed tells them apart
    sig = [s["noise_sigma"] for s in doc["steps"]]
    assert sig[-1]["positions"] == pytest.approx(0.005, rel=0.1)
    assert sig[-1]["angles"] == pytest.approx(np.deg2rad(2 / 3600), rel=0.1)
    assert sig[0]["positions"] > 10 * sig[-1]["positions"]  # the spiral term unmodelled
    assert sig[0]["positions"] > sig[1]["positions"] > sig[2]["positions"]
    printed = capsys.readouterr().err
    assert "RMS = 0.97" in printed and "(σ estimated for this model: positions 4.9" in printed
    assert text.count("σ estimated for this model: positions") == 3
    # each step's σ against the file's 5 µm, as the JSON has it: the final model's about 1×
    ratios = [float(r) for r in re.findall(r"positions [\d.]+ µm = ([\d.]+)× the stated", text)]
    assert ratios == pytest.approx([s["positions"] / 0.005 for s in sig], rel=0.05), ratios
    assert ratios[-1] == pytest.approx(1.0, rel=0.1)


def test_diagnose_cli_refuses_bad_input(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    text = EXAMPLE.read_text().splitlines()
    cols = text[0].split(",")
    row = text[3].split(",")
    row[cols.index("cmd_y")] = "abc"
    bad.write_text("\n".join([text[0], text[1], text[2], ",".join(row)] + text[4:]) + "\n")
    assert main(["diagnose", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "row 3" in err and "cmd_y" in err
    assert main(["diagnose", "--effects", "friction", "--out", str(tmp_path / "o")]) == 2
    assert "unknown effect 'friction'" in capsys.readouterr().err


def test_structure_left_on_too_few_stops_for_the_gp_is_said_not_raised():
    """The GP residual model needs two stops a fold; where the structure left unexplained
    is on fewer (20 stops, 11 folds; a thermal drift with nothing in the library to name
    it), `diagnose` says so and returns the diagnosis without it (it raised the GP's
    ValueError and the command line exited with an error)."""
    nominal = _nominal()
    n = 20
    true = perturb_table(nominal, 5)
    data = simulate(
        nominal,
        true,
        plan_random(n, 4),
        tracker6(),
        effects={"spiral": jt.Spiral(12.7), "thermal": jt.Thermal(np.full(6, 3e-5))},
        compensated=False,
        seed=4,
        temperature=20 + 15 * np.arange(n) / n,
    )
    said = []
    diag = diagnose(nominal, data, log=said.append, library=[], discover=False, folds=11)
    assert diag.unexplained and diag.residual_model is None
    assert any("too few stops for a GP residual model (20: it needs 22" in s for s in said), said


def test_data_of_a_new_size_run_no_eager_operations():
    """Simulating, fitting and diagnosing data of a size no other test uses, and the batch
    APIs on it, lower no single jax.numpy operation run eagerly (each would compile a
    program for that size: ~20 ms from an empty cache, a third of a second for the ~60 a
    first `jaxtable diagnose` ran before they were taken out)."""
    from conftest import compiled_programs

    from benchmarks.compile_profile import is_eager_operation

    n = 67
    nominal = _nominal()
    true = perturb_table(nominal, 3, joint_sigma=0.010, zero_sigma=0.050)
    eff = {"spiral": jt.Spiral(12.7), "backlash": jt.Backlash(np.full(6, 0.02))}
    temperature = 20 + 10 * np.arange(n) / n
    with compiled_programs("jaxpr_to_mlir_module") as lowered:
        data = simulate(
            nominal,
            true,
            plan_random(n, 3),
            tracker6(),
            effects=eff,
            seed=3,
            temperature=temperature,
        )
        jt.calibrate(nominal, data)
        diagnose(nominal, data, log=_quiet)
        cmd = jt.actuator_command(nominal, data.cmd_pose)
        res = jt.forward_solve(nominal, cmd)
        np.testing.assert_allclose(np.asarray(res.pose), data.cmd_pose, atol=1e-9)
        assert bool(np.all(np.asarray(res.ok)))
        jt.pose_error(res.pose, data.cmd_pose)
        jt.leg_lengths(nominal, data.cmd_pose)
    eager = [name for name in lowered if is_eager_operation(name)]
    assert eager == [], eager
