"""The σ-free structure test and the noise estimate, measured over seeds on simulated tracker
data (the reference table with random geometric errors: joints σ 10 µm, L0 σ 50 µm; a 6-D
tracker's noise) where the truth is known:

- noise-only data with σ stated wrong per group (positions 25 % too small, angles 25 % too
  large): the structure test's false-alarm rate is its nominal α and the discovery
  dictionary claims a term in at most 5 % of data sets (counted over 100 seeds in the
  default run, 300 under `slow`), and the variance-component 95 % interval of the ratio
  estimated / stated σ covers the true ratio at its nominal rate;
- the test does not move when the stated σ is scaled or absent;
- noise correlated between a row's columns (x with pitch, y with roll) raises no alarm;
- each library effect the rigid model lacks is seen, and the hint names the variable it
  depends on.
"""

import dataclasses

import numpy as np
import pytest
from scipy.stats import binom

import jaxtable as jt
from jaxtable import _params as params
from jaxtable._calibration.fit import fit, setup
from jaxtable._calibration.instruments import Instrument, tracker6
from jaxtable._calibration.simulate import perturb_table, plan_random, simulate
from jaxtable._context import run_time
from jaxtable._discovery.diagnose import discovery_setup
from jaxtable._discovery.dictionary import Bases, candidates, screen
from jaxtable._discovery.structure import (
    agreements,
    clock_rows,
    features,
    neighbours,
    null_law,
    structure_test,
    whitened,
)

N = 150
WRONG = np.array([0.75, 0.75, 0.75, 1.25, 1.25, 1.25])  # stated / true σ per column


def _null(seed, instrument=None):
    nominal = jt.reference_table()
    true = perturb_table(nominal, seed, joint_sigma=0.010, zero_sigma=0.050)
    rng = np.random.default_rng(seed)
    data = simulate(
        nominal,
        true,
        plan_random(N, seed),
        instrument or tracker6(),
        effects={},
        compensated=False,
        temperature=20 + 5 * np.arange(N) / N + rng.normal(0, 0.1, N),
        seed=seed,
    )
    return nominal, data


def _fit(nominal, data, noise="estimate"):
    st = setup(nominal, data, jt.GEOMETRY, effects={}, compensated=False)
    return st, fit(st, noise=noise)


def _null_runs(seeds):
    """Per noise-only data set with the σ stated wrong by WRONG, fitted once: the structure
    test's p-value, the VCE ratio intervals (G, 2), and whether the discovery dictionary's
    screening claims a term (its dictionary-wide threshold at 5 %)."""
    p, intervals, hits = [], [], []
    free = jt.GEOMETRY + tuple(f"discovered.{f}" for f in jt.Discovered.fields)
    for seed in seeds:
        nominal, data = _null(seed)
        data = dataclasses.replace(data, sigma=data.sigma * WRONG)
        st = setup(
            nominal, data, free, effects={"discovered": jt.Discovered.null()}, compensated=False
        )
        cal = fit(st, st.free_mask(jt.GEOMETRY))
        p.append(structure_test(cal, st, draws=500, seed=seed).p_value)
        intervals.append(cal.noise.ratio_interval)
        scr = screen(cal, st, candidates(st, data), draws=500, seed=seed)
        hits.append(bool(scr.score[scr.best()] > scr.threshold))
    return np.array(p), np.array(intervals), np.array(hits)


def _check_null(seeds):
    p, intervals, hits = _null_runs(seeds)
    n = len(seeds)
    # false alarms at alpha = 5 %: an upper limit a correct test exceeds with probability
    # < 1 % and a test with twice the rate fails most of the time
    alarms = int(np.sum(p < 0.05))
    assert alarms <= binom.ppf(0.99, n, 0.05), (alarms, n)
    # p-values spread over (0, 1): not a test that never rejects
    assert 0.35 < np.mean(p < 0.5) < 0.65, np.mean(p < 0.5)
    # the discovery dictionary: any term claimed in at most 5 % of the data sets, the whole
    # dictionary counted
    assert hits.sum() <= binom.ppf(0.99, n, 0.05), (hits.sum(), n)
    # VCE: the 95 % interval of estimated / stated σ covers the truth (1 / WRONG per group)
    truth = 1.0 / np.array([WRONG[0], WRONG[3]])
    covered = (intervals[:, :, 0] <= truth) & (truth <= intervals[:, :, 1])
    k, m = int(covered.sum()), covered.size
    assert binom.ppf(0.005, m, 0.95) <= k <= binom.ppf(0.995, m, 0.95), (k, m)
    # the stated σ are found inconsistent (each group is 25 % off) in almost every data set
    inconsistent = (intervals[:, :, 0] > 1.0) | (intervals[:, :, 1] < 1.0)
    assert inconsistent.mean() > 0.95, inconsistent.mean()


def test_false_alarm_rates_and_noise_interval_coverage_100_seeds():
    _check_null(range(100))


@pytest.mark.slow
def test_false_alarm_rates_and_noise_interval_coverage_300_seeds():
    _check_null(range(100, 400))


def test_structure_test_ignores_the_scale_of_sigma():
    """The same statistic whatever scale the stated σ has: exactly when the weights are used
    as stated (a common factor cancels) and when σ is estimated (the estimate is the same
    whether σ was stated 25 % off or not at all)."""
    nominal, data = _null(7)

    def agreement(sigma, noise):
        st, cal = _fit(nominal, dataclasses.replace(data, sigma=sigma), noise)
        return [v["agreement"] for v in structure_test(cal, st).families.values()]

    scales = (1.0, 0.75, 1.25)
    fixed = [agreement(data.sigma * f, "fixed") for f in scales]
    np.testing.assert_allclose(fixed, [fixed[0]] * 3, rtol=1e-9)
    est = [agreement(data.sigma * f, "estimate") for f in scales]
    np.testing.assert_allclose(est, [est[0]] * 3, rtol=1e-6)
    # no σ stated: the estimate settles the group weights to VCE's 1 % tolerance, which
    # moves the statistic by far less than its null spread (~0.05 here)
    np.testing.assert_allclose(agreement(None, "estimate"), est[0], atol=1e-3)


def test_noise_correlated_within_a_row_raises_no_alarm():
    """Tracker noise with x–pitch and y–roll correlation 0.8: over 40 seeds no more alarms
    at α = 5 % than a correct test gives with probability 99 %."""
    clean = Instrument("clean 6-D", (0, 1, 2, 3, 4, 5), (0.0,) * 6)
    sd = np.array([0.01, 0.01, 0.01, 1e-5, 1e-5, 1e-5])
    R = np.eye(6)
    R[0, 4] = R[4, 0] = 0.8
    R[1, 3] = R[3, 1] = -0.8
    L = np.linalg.cholesky(R) * sd[:, None]
    p = []
    for seed in range(40):
        nominal, data = _null(500 + seed, clean)
        noise = np.random.default_rng(seed).standard_normal((N, 6)) @ L.T
        data = dataclasses.replace(
            data, measured=data.measured + noise, sigma=np.broadcast_to(sd, (N, 6)).copy()
        )
        st, cal = _fit(nominal, data)
        p.append(structure_test(cal, st, draws=500).p_value)
    alarms = int(np.sum(np.array(p) < 0.05))
    assert alarms <= binom.ppf(0.99, 40, 0.05), (alarms, p)


@pytest.mark.parametrize(
    "name, effect, hint",
    [
        ("backlash", jt.Backlash(np.full(6, 0.02)), {"extensions, direction"}),
        (
            "lead_scale",
            jt.LeadScale(np.array([1.2e-4, -1e-4, 0.8e-4, -1.2e-4, 1e-4, -0.8e-4])),
            {"extensions"},
        ),
        ("thermal", jt.Thermal(np.full(6, 11.5e-6)), {"temperature", "time"}),
        ("spiral", jt.Spiral(12.7), {"extensions", "extensions, direction"}),
    ],
)
def test_a_missing_effect_is_seen_and_its_variable_hinted(name, effect, hint):
    nominal = jt.reference_table()
    true = perturb_table(nominal, 3, joint_sigma=0.010, zero_sigma=0.050)
    data = simulate(
        nominal,
        true,
        plan_random(N, 3),
        tracker6(),
        effects={name: effect},
        compensated=False,
        temperature=20 + 10 * np.arange(N) / N,
        seed=3,
    )
    st, cal = _fit(nominal, data)
    result = structure_test(cal, st)
    assert result.structure, result.families
    assert result.hints[0] in hint, result.hints


def test_the_linearised_test_of_an_added_effect_equals_the_test_on_its_refit():
    """`detection_power` tests a candidate's fit without refitting: residuals
    (I − Q Qᵀ) e of the base fit (Q: what the candidate's columns add to its column space)
    against `null_law(..., Q=Q)`. On data whose thermal drift the base fit leaves as strong
    structure (z ≈ 8), that gives the refit's agreements within one null std per family and
    the same verdict (no structure left), and the null law with Q matches the refit's."""
    nominal = jt.reference_table()
    true = perturb_table(nominal, 3, joint_sigma=0.010, zero_sigma=0.050)
    rng = np.random.default_rng(3)
    data = simulate(
        nominal,
        true,
        plan_random(100, 3),
        tracker6(),
        effects={"thermal": jt.Thermal(np.full(6, 3.5e-6))},
        compensated=False,
        temperature=20 + 10 * np.arange(100) / 100 + rng.normal(0, 0.2, 100),
        seed=3,
    )
    st = discovery_setup(nominal, data, compensated=False)
    base = fit(st, st.free_mask(jt.GEOMETRY))
    refit = fit(st, st.free_mask(jt.GEOMETRY + params.effect_parameters("thermal[all]")))
    w0, w1 = whitened(base, st), whitened(refit, st)
    index = {k: i for i, k in enumerate(st.names)}
    cols = [index[k] for k in params.form_keys(st.names, "thermal[all]")]
    Q = Bases.of(np.asarray(base.jacobian_full) * w0.factor.reshape(-1, 1), w0.U, [cols]).Q
    nns = {f: neighbours(x, 3, w0.rows) for f, x in features(st).items()}
    e0 = w0.e.reshape(-1)
    law0, law_q, law1 = (
        null_law(w, nns, 2000, 5, Q=q) for w, q in ((w0, None), (w0, Q), (w1, None))
    )
    a0 = agreements(w0, nns)
    a_lin = agreements(w0, nns, (e0 - Q @ (Q.T @ e0)).reshape(-1, 6))
    a_refit = agreements(w1, nns)
    assert law0.z(a0) > 5 and law0.p_value(law0.z(a0)) < 0.01  # the base leaves structure
    for f in nns:
        assert abs(a_lin[f] - a_refit[f]) < law1.std[f], (f, a_lin[f], a_refit[f], a0[f])
        assert abs(law_q.mean[f] - law1.mean[f]) < 0.1 * law1.std[f]
        assert abs(law_q.std[f] / law1.std[f] - 1) < 0.05
    assert law_q.p_value(law_q.z(a_lin)) >= 0.01 and law1.p_value(law1.z(a_refit)) >= 0.01


def test_neighbours_are_the_nearest_other_rows():
    """The k nearest other rows against a full distance matrix sorted by scipy, on a subset
    of rows, with a stop repeated once (a distance 0 that is not the row itself) and one
    repeated six times (more rows at distance 0 than k + 1: the row itself must still not
    be its own neighbour)."""
    from scipy.spatial.distance import cdist

    rng = np.random.default_rng(4)
    x = rng.normal(size=(3000, 12))
    x[10] = x[11]  # a stop repeated
    x[20:26] = x[20]  # six stops at one pose
    rows = np.sort(rng.choice(3000, 2500, replace=False))
    rows = np.union1d(rows, [10, 11, *range(20, 26)])
    nn = neighbours(x, 3, rows)
    assert nn.shape == (len(rows), 3)
    d = cdist(x[rows], x[rows])
    np.fill_diagonal(d, np.inf)
    truth = np.sort(d, axis=1)[:, :3]
    np.testing.assert_array_equal(np.sort(np.take_along_axis(d, nn, axis=1), axis=1), truth)
    assert np.all(nn != np.arange(len(rows))[:, None])  # never the row itself
    assert np.all([len(set(r)) == 3 for r in nn.tolist()])  # three different rows
    i10 = np.flatnonzero(rows == 10)[0]
    assert rows[nn[i10]].tolist().count(11) == 1 and 10 not in rows[nn[i10]]
    for i in np.flatnonzero((rows >= 20) & (rows < 26)):
        assert set(rows[nn[i]]) <= set(range(20, 26)) - {rows[i]}


def test_agreement_is_the_neighbour_sum_written_out():
    """A = Σ_i Σ_{j ∈ NN(i)} e_i·e_j / (k Σ_i |e_i|²), written out row by row, for a batch
    of residual sets (the Monte Carlo draws) and for one."""
    from jaxtable._discovery.structure import _agreement

    rng = np.random.default_rng(5)
    e = rng.normal(size=(4, 30, 6))
    nn = neighbours(rng.normal(size=(30, 2)), 3, np.arange(30))
    by_hand = [
        sum(e[b, i] @ e[b, j] for i in range(30) for j in nn[i]) / (3 * np.sum(e[b] ** 2))
        for b in range(4)
    ]
    np.testing.assert_allclose(_agreement(e, nn), by_hand, rtol=1e-12)
    np.testing.assert_allclose(_agreement(e[2], nn), by_hand[2], rtol=1e-12)


def test_neighbours_in_time_are_neighbours_on_the_log_s_clock():
    """Six stops, three then three after a pause: on the clock the stop before the pause has
    its two predecessors as neighbours, in row order the one after the pause; without a
    clock the time feature is the row index itself (equal steps tie exactly)."""
    clock = run_time(6, [0.0, 60, 120, 3000, 3060, 3120])
    rows = np.arange(6)
    near = neighbours(clock_rows(clock)[:, None], 2, rows)
    assert sorted(near[2]) == [0, 1] and sorted(near[3]) == [4, 5]
    ordered = clock_rows(run_time(6))
    np.testing.assert_array_equal(ordered, rows)
    assert sorted(neighbours(ordered[:, None], 2, rows)[2]) == [1, 3]
