"""Shared forms of library effects: six identical cylinders share one screw, one expansion
coefficient and one stiffness. A fit may tie such a per-leg field to one number for all legs
(`thermal.alpha[all]`), and `diagnose` lets ΔBIC choose between the forms. Checked against
the chain rule (a shared column is the sum of the per-leg columns), data simulated with
known parameters (z-scores over seeds) and the form the simulated truth has."""

import numpy as np
import pytest
from scipy.stats import binom, kstest

import jaxtable as jt
from jaxtable import _params as params
from jaxtable._calibration.fit import fit
from jaxtable._calibration.instruments import tracker6
from jaxtable._calibration.simulate import perturb_table, plan_random, simulate
from jaxtable._discovery.diagnose import diagnose, discovery_setup, equal_legs_p
from jaxtable._reports.diagnose import markdown

N = 100


def _nominal():
    return jt.replace(jt.reference_table(), platform_mass=150.0, platform_cog=[0.0, 0.0, 60.0])


def _run(effects, seed, n=N):
    nominal = _nominal()
    true = perturb_table(nominal, seed, joint_sigma=0.010, zero_sigma=0.050)
    rng = np.random.default_rng(seed)
    t = np.arange(n) / n
    data = simulate(
        nominal,
        true,
        plan_random(n, seed),
        tracker6(),
        effects=effects,
        compensated=False,
        seed=seed,
        temperature=20 + 10 * t + 1.5 * np.sin(6 * np.pi * t) + rng.normal(0, 0.2, n),
        payload=rng.choice([0.0, 50.0, 100.0], n),
    )
    return nominal, data


def _calibrate_thermal(nominal, data, free):
    return jt.calibrate(
        nominal,
        data,
        params.GEOMETRY + (free,),
        effects={"thermal": jt.Thermal()},
        compensated=False,
    )


def _diagnose_thermal(alpha, seed=3):
    """`diagnose` with the thermal effect as the only candidate, on a run with `alpha`."""
    nominal, data = _run({"thermal": jt.Thermal(alpha)}, seed)
    return diagnose(
        nominal,
        data,
        library=["thermal"],
        discover=False,
        flexible=False,
        compensated=False,
        log=lambda _: None,
    )


def test_names_of_the_shared_forms():
    assert params.effect_forms("thermal") == ("thermal", "thermal[all]")
    assert params.effect_forms("compliance") == ("compliance", "compliance[all]")
    assert params.effect_forms("spiral") == ("spiral", "spiral[all]")
    assert params.effect_forms("backlash") == ("backlash",)  # each nut its own lost motion
    assert params.effect_parameters("thermal[all]") == ("thermal.alpha[all]",)
    assert params.effect_parameters("thermal") == ("thermal.alpha",)
    assert params.label("thermal.alpha[all]") == "thermal alpha, all legs"
    assert params.split("compliance.flex[all]") == ("compliance", "flex")
    keys = ["thermal.alpha[1]", "thermal.alpha[2]", "thermal.alpha[all]", "spiral.lead[1]"]
    assert params.form_keys(keys, "thermal[all]") == ["thermal.alpha[all]"]
    assert params.form_keys(keys, "thermal") == ["thermal.alpha[1]", "thermal.alpha[2]"]
    assert params.with_form(["spiral", "thermal[all]"], "thermal") == ["spiral", "thermal"]
    assert params.form_label("thermal[all]") == "thermal (one alpha for all legs)"
    table, effects = _nominal(), {"thermal": jt.Thermal(), "backlash": jt.Backlash()}
    params.check(table, effects, ["thermal.alpha[all]"], allow_shared=True)
    with pytest.raises(ValueError, match="can only be fitted"):
        params.check(table, effects, ["thermal.alpha[all]"])  # e.g. a sensitivity
    with pytest.raises(ValueError, match="shared fields"):
        params.check(table, effects, ["backlash.w[all]"], allow_shared=True)
    with pytest.raises(ValueError, match="shared fields"):
        params.check(table, effects, ["zero_lengths[all]"], allow_shared=True)


def test_a_shared_column_is_the_sum_of_the_per_leg_columns():
    """Chain rule: one step on every leg's value moves the readings as the six per-leg steps
    together. Checked on the full Jacobian of the discovery set-up, where both forms sit."""
    nominal, data = _run({}, 0, n=40)
    st = discovery_setup(nominal, data, compensated=False)
    cal = fit(st, st.free_mask(params.GEOMETRY), noise="fixed")
    J = np.asarray(cal.jacobian_full)
    index = {k: i for i, k in enumerate(st.names)}
    for name in ("spiral.lead", "thermal.alpha", "compliance.flex"):
        shared = J[:, index[name + "[all]"]]
        per_leg = J[:, [index[f"{name}[{i}]"] for i in range(1, 7)]].sum(axis=1)
        assert np.linalg.norm(per_leg) > 0, name
        np.testing.assert_allclose(shared, per_leg, rtol=0, atol=1e-9 * np.abs(per_leg).max())


def test_shared_thermal_fit_recovers_the_common_coefficient():
    """Eight data sets with one α for all legs: the shared fit's z-scores against the truth
    behave as N(0, 1) (|z| < 3.5 each; their RMS within the 99 % range of χ²₈: 0.52-1.58),
    the six legs' values stay equal, and the shared coefficient is better determined than
    any leg's own."""
    alpha = 11.5e-6
    z = []
    for seed in range(8):
        nominal, data = _run({"thermal": jt.Thermal(alpha)}, 10 + seed)
        cal = _calibrate_thermal(nominal, data, "thermal.alpha[all]")
        v, s = cal.parameter("thermal.alpha")
        assert v.shape == (1,) and np.all(np.isfinite(s))
        np.testing.assert_array_equal(np.asarray(cal.effects["thermal"].alpha), np.full(6, v[0]))
        z.append((v[0] - alpha) / s[0])
        if seed == 0:
            per_leg = _calibrate_thermal(nominal, data, "thermal.alpha")
            assert s[0] < per_leg.parameter("thermal.alpha")[1].min()
    z = np.asarray(z)
    assert np.all(np.abs(z) < 3.5), z
    assert 0.45 < np.sqrt(np.mean(z**2)) < 1.65, z


@pytest.mark.parametrize(
    "spread, form",
    [(np.zeros(6), "thermal[all]"), (0.3 * np.array([1, -1, 1, -1, 1, -1]), "thermal")],
)
def test_diagnose_fits_the_form_the_data_support(spread, form):
    """One α for all legs: the shared form is selected (five parameters fewer at no loss of
    fit), its coefficient within 3.5σ of the truth and the saved model carries it on every
    leg. α differing by ±30 % between legs (±25 µm over the run): the per-leg form."""
    alpha = 11.5e-6 * (1.0 + spread)
    diag = _diagnose_thermal(alpha)
    assert diag.selected == ["thermal"], diag.selected
    assert diag.selected_forms == [form], diag.selected_forms
    assert diag.as_json()["selected_forms"] == [form]
    v, s = diag.effect_params("thermal")["alpha"]
    assert v.shape == ((1,) if form.endswith("[all]") else (6,))
    assert np.all(np.abs(v - (alpha[0] if v.shape == (1,) else alpha)) < 3.5 * s), (v, s)
    saved = np.asarray(diag.fitted_model().effects["thermal"].alpha)
    np.testing.assert_allclose(saved, np.broadcast_to(v, (6,)), rtol=1e-12)
    assert not diag.unexplained
    # the test of equal legs on the first step: the per-leg form against the shared one
    first = {c.effect: c for c in diag.steps[0].candidates}
    p_equal = first["thermal"].equal_legs_p
    assert first["thermal"].as_json()["equal_legs_p"] == p_equal
    assert first["thermal[all]"].equal_legs_p is None
    assert (p_equal < 0.01) == (form == "thermal"), p_equal
    text = markdown(diag, [], "test")
    assert ("the data do not reject equal legs" in text) == (form == "thermal[all]")


def test_a_weak_shared_effect_that_leaves_no_structure_is_named():
    """With σ estimated, χ² = dof, so the share of the excess χ² is a share of the noise
    floor 3 √(2 dof) and asks for Δχ² ≥ 30 here. A shared α an order of magnitude below the
    usual (ΔBIC −15, Δχ² 22) falls short of it; it is named because the structure test sees
    nothing left once it is in (the rule's second clause), at a value within 3.5σ."""
    alpha = 0.085 * 11.5e-6
    diag = _diagnose_thermal(alpha)
    assert diag.selected_forms == ["thermal[all]"], diag.selected_forms
    cand = next(c for c in diag.steps[0].candidates if c.effect == "thermal[all]")
    assert cand.delta_bic < -10 and cand.share < 0.3, (cand.delta_bic, cand.share)
    assert cand.structure_after is not None and cand.structure_after >= 0.01
    assert cand.as_json()["structure_p_after"] == cand.structure_after
    v, s = diag.effect_params("thermal")["alpha"]
    assert abs(v[0] - alpha) < 3.5 * s[0], (v, s)


def _equal_legs_p(seed: int, flex) -> float:
    """`diagnose`'s test of equal legs on one run with compliance `flex` (6,): the shared
    form fitted with σ estimated, the per-leg form in the same weights."""
    nominal, data = _run({"compliance": jt.Compliance(flex)}, seed)
    st = discovery_setup(nominal, data, compensated=False)
    shared = fit(st, st.free_mask(params.GEOMETRY + params.effect_parameters("compliance[all]")))
    per_leg = fit(
        st,
        st.free_mask(params.GEOMETRY + params.effect_parameters("compliance")),
        noise="fixed",
        weight=shared.weight,
    )
    return equal_legs_p(per_leg, shared)


@pytest.mark.slow
def test_equal_legs_are_rejected_at_the_stated_rate():
    """Six identical cylinders (k = 2e4 N/mm), 60 runs: the likelihood-ratio p-values that
    decide a shared form's upgrade to per leg are uniform (Kolmogorov-Smirnov p > 0.01) and
    at most the binomial 99 % bound of 60 runs at 1 % fall below 0.01 (3); legs ±30 %
    apart are told apart in each of 5 runs."""
    p = np.array([_equal_legs_p(200 + seed, np.full(6, 5e-5)) for seed in range(60)])
    assert kstest(p, "uniform").pvalue > 0.01, np.sort(p)
    assert np.sum(p < 0.01) <= binom.ppf(0.99, 60, 0.01), np.sort(p)
    apart = 5e-5 * (1 + 0.3 * np.array([1, -1, 1, -1, 1, -1]))
    assert all(_equal_legs_p(300 + seed, apart) < 0.01 for seed in range(5))
