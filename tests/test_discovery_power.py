"""Detection power of diagnose's first round (`jaxtable.detection_power`): the noise-only rate
against the stated false-discovery rate, power against the noncentral χ² law a single term's
score follows, and the amplitude scale against the nonlinear simulation."""

import math

import numpy as np
import pytest

import jaxtable as jt

N = 100
S2 = {"discovered": jt.Discovered(s2=[0, 0, 1.0, 0, 0, 0])}


def _data(nominal, effects, seed=7):
    rng = np.random.default_rng(seed)
    return jt.simulate(
        nominal,
        nominal,
        jt.plan_random(N, seed),
        jt.tracker6(),
        effects=effects,
        compensated=False,
        seed=seed,
        temperature=20 + 10 * np.arange(N) / N + rng.normal(0, 0.2, N),
        payload=rng.choice([0.0, 50.0, 100.0], N),
    )


@pytest.fixture(scope="module")
def power():
    nominal = jt.replace(jt.reference_table(), platform_mass=150.0, platform_cog=[0, 0, 60.0])
    data = _data(nominal, {})
    planted = {"s^2 on leg 3": S2, "backlash": {"backlash": jt.Backlash(np.ones(6))}}
    p = jt.detection_power(
        nominal, data, planted, amplitudes=[1.0, 1.5, 8.0], trials=4000, draws=4000
    )
    return nominal, p


def test_noise_only_rate_is_the_stated_rate(power):
    _, p = power
    # 4000 noise-only trials: binomial sd 0.0034 at the stated 5 %; a 33 % (or 10 %) rate
    # cannot land in this window
    assert 0.037 <= p.false_term <= 0.063, p.false_term
    assert p.false_library <= 0.005, p.false_library
    assert p.false_discovery <= p.false_term + p.false_library + 1e-12


def test_single_term_power_follows_the_noncentral_chi2_law(power):
    """A one-coefficient term's Δχ² is (N(μ, 1))² (μ = amplitude · visible); it beats
    threshold + ln n_obs with the law's probability. Naming it takes that and being the best
    candidate, so P(named right) ≤ law; something is named whenever it beats the threshold,
    so P(named right or wrong) ≥ law (a correlated rival, `d*s` on the same leg, wins some
    of those trials)."""
    _, p = power
    k = p.labels.index("s^2 on leg 3")
    c = math.sqrt(p.threshold + math.log(p.n_obs))

    def phi(x):
        return 0.5 * (1 + math.erf(x / math.sqrt(2)))

    for ai, a in enumerate(p.amplitudes):
        mu = a * p.visible[k]
        law = phi(mu - c) + phi(-mu - c)
        sd = math.sqrt(max(law * (1 - law), 0.01) / p.trials)
        named = p.correct[k, ai] + p.wrong[k, ai]
        assert p.correct[k, ai] <= law + 4 * sd, (a, law, p.correct[k])
        assert named >= law - 4 * sd, (a, law, named)
        assert p.wrong[k, ai] <= 0.15, (a, p.wrong[k], p.wrong_names[k])
    # the comparison is made where the law is not flat
    assert np.any((p.correct[k, :2] > 0.2) & (p.correct[k, :2] < 0.9)), p.correct[k]
    assert p.correct[k, -1] >= 0.99 and p.wrong[k, -1] <= 0.01


def test_library_effect_named_at_large_amplitude(power):
    _, p = power
    k = p.labels.index("backlash")
    assert p.truth[k] == "backlash"
    assert p.correct[k, -1] >= 0.99 and p.wrong[k, -1] <= 0.01
    assert np.all(np.diff(p.correct[k]) >= -0.02)  # more signal never names it less often
    assert p.amplitude_at("backlash", 0.9) <= 8.0


def test_amplitude_scale_matches_the_simulation(power):
    """The coefficient `coefficient_at` gives for 3σ moves the simulated readings by 3σ at
    their peak (nonlinear model, same noise draw with and without it)."""
    nominal, p = power
    coef = p.coefficient_at("s^2 on leg 3", 3.0)
    with_it = _data(nominal, {"discovered": jt.Discovered(s2=[0, 0, coef, 0, 0, 0])})
    without = _data(nominal, {})
    diff = (with_it.measured - without.measured) / with_it.sigma
    assert abs(np.nanmax(np.abs(diff)) / 3.0 - 1.0) < 0.02


def test_signal_to_noise_is_that_of_the_simulated_noise(power):
    """The trials' noncentrality (amplitude · visible)² is the Δχ² the planted term adds in
    units of the noise the simulation draws (its stated σ): the nonlinear readings' change at
    3σ, in σ units, projected off the base fit's columns. (Rescaling σ to one run's residuals
    would miss it by that run's chance σ error, ±6 % here.)"""
    from jaxtable._calibration.fit import fit
    from jaxtable._discovery.diagnose import discovery_setup

    nominal, p = power
    k = p.labels.index("s^2 on leg 3")
    coef = p.coefficient_at("s^2 on leg 3", 3.0)
    with_it = _data(nominal, {"discovered": jt.Discovered(s2=[0, 0, coef, 0, 0, 0])})
    without = _data(nominal, {})
    diff = np.nan_to_num((with_it.measured - without.measured) / with_it.sigma).reshape(-1)
    st = discovery_setup(nominal, without, compensated=False)
    base = fit(st, st.free_mask(jt.GEOMETRY), noise="fixed")
    Q, _ = np.linalg.qr(np.asarray(base.jacobian))
    seen = diff - Q @ (Q.T @ diff)
    assert abs((3.0 * p.visible[k]) ** 2 / (seen @ seen) - 1.0) < 0.03


def test_bad_plants_are_refused(power):
    nominal, _ = power
    data = _data(nominal, {})
    one = jt.simulate(nominal, nominal, jt.plan_random(20, 1), jt.tracker6(), effects={})
    with pytest.raises(ValueError, match="cannot name thermal"):
        jt.detection_power(nominal, one, {"th": {"thermal": jt.Thermal(np.ones(6))}}, trials=10)
    with pytest.raises(ValueError, match="exactly one dictionary candidate"):
        jt.detection_power(
            nominal,
            data,
            {"two": {"discovered": jt.Discovered(s2=[1.0, 0, 1.0, 0, 0, 0])}},
            trials=10,
        )
    with pytest.raises(ValueError, match="amplitudes"):
        jt.detection_power(nominal, data, {"s2": S2}, amplitudes=[-1.0], trials=10)
