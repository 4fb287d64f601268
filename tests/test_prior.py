"""A Gaussian prior on the geometry from the tolerance budget (`calibrate(..., prior=)`):
the maximum a posteriori fit, its posterior covariance, and what it does with data that
determine few combinations (the paper's own measurement: x readings on an x line)."""

import dataclasses
import warnings
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtable as jt
from jaxtable._calibration.fit import fit, jacobian_in_chunks, setup
from jaxtable._calibration.fit import validate as rms_of
from jaxtable._calibration.prior import weights
from jaxtable._calibration.simulate import perturb_table
from jaxtable.cli import main

TOL = jt.Tolerances()
L0_SIGMA = float(np.hypot(TOL.zero_length, TOL.clearance / 2))  # the budget's leg offset
SEEDS = range(12)


def x_only(table, true, n=60, seed=0):
    """`n` stops on the x line (±100 mm), the 6-D tracker's x reading alone (σ unstated)."""
    plan = np.zeros((n, 6))
    plan[:, 0] = np.linspace(-100.0, 100.0, n)
    d = jt.simulate(table, true, plan, jt.tracker6(), seed=seed)
    m = d.measured.copy()
    m[:, 1:] = np.nan
    return dataclasses.replace(d, measured=m, sigma=None)


def truth_steps(table, true, names):
    """The true value of each flat parameter (a step from the nominal table; joint sets
    not gauged on an x line: their basis is the identity over the (6, 3) coordinates)."""
    steps = {
        "base_joints": (np.asarray(true.base_joints) - table.base_joints).reshape(-1),
        "platform_joints": (np.asarray(true.platform_joints) - table.platform_joints).reshape(-1),
        "zero_lengths": np.asarray(true.zero_lengths) - table.zero_lengths,
    }
    out = []
    for n in names:
        head, _, rest = n.partition(".g")
        if rest:
            out.append(steps[head][int(rest) - 1])
        else:
            out.append(steps[n.partition("[")[0]][int(n.partition("[")[2][:-1]) - 1])
    return np.array(out)


def test_prior_weights_follow_the_tolerance_budget():
    """1/σ per flat key, by hand: joints 10 µm, zero lengths √(10² + 50²) µm (zero length
    and the ±w/2 clearance), the lead-scale error 25 µm / 300 mm, the spiral lead 0.0127
    mm/rev; frames, targets and other effects none. σ = 0 would pin: refused."""
    names = ["base_joints.g3", "platform_joints.g12", "zero_lengths[4]", "frame[1].x",
             "lead_scale.eps[2]", "spiral.lead[all]", "thermal.alpha[all]", "target.z"]  # fmt: skip
    w = weights(names, TOL)
    expected = [100.0, 100.0, 1 / np.sqrt(0.01**2 + 0.05**2), 0, 300 / 0.025, 1 / 0.0127, 0, 0]
    np.testing.assert_allclose(w, expected, rtol=1e-12)
    assert not weights(names, None).any()
    with pytest.raises(ValueError, match="zero_lengths is 0"):
        weights(names, jt.Tolerances(zero_length=0.0, clearance=0.0))
    with pytest.raises(TypeError, match="Tolerances"):
        weights(names, {"base_joints": 0.01})


@pytest.fixture(scope="module")
def x_line_fits(table):
    """Tables drawn from the prior itself (joints σ 10 µm, leg offsets σ 51 µm), each
    measured on its x line; fitted with the prior and (the first) without."""
    out = []
    for seed in SEEDS:
        true = perturb_table(table, seed=seed, joint_sigma=TOL.base_joints, zero_sigma=L0_SIGMA)
        st = setup(table, x_only(table, true, seed=seed), prior=TOL, compensated=True)
        out.append((true, st, fit(st)))
    return out


def test_the_map_fit_is_where_chi2_plus_the_prior_is_stationary(table, x_line_fits):
    """At the fit, the gradient of χ² + Σ(θ/σ)² is zero, Jᵀr + Λθ = 0 (J and r evaluated
    anew at the fitted θ, with the fit's weights: the σ it estimated; to 1e-6 of either
    term), and the covariance is (JᵀJ + Λ)⁻¹ (to
    1e-6), the posterior's: the frame's x offset has no prior, the 42 geometric
    parameters do."""
    true, st, cal = x_line_fits[0]
    problem = eqx.tree_at(lambda p: p.weight, st.problem, jnp.asarray(cal.weight))
    J, r, _ = jacobian_in_chunks(problem, st.layout, cal.theta)
    assert cal.names == st.names  # every parameter free
    lam = np.asarray(st.prior) ** 2
    assert np.count_nonzero(lam) == 42 and lam[st.names.index("frame[1].x")] == 0
    grad_data, grad_prior = J.T @ r, lam * cal.value
    scale = np.maximum(np.abs(grad_data), np.abs(grad_prior)).max()
    assert np.max(np.abs(grad_data + grad_prior)) < 1e-6 * scale
    post = np.linalg.inv(J.T @ J + np.diag(lam))
    np.testing.assert_allclose(cal.covariance, post, rtol=1e-6, atol=1e-6 * np.abs(post).max())
    assert cal.converged and np.all(np.isfinite(cal.std))


def test_the_posterior_covers_tables_drawn_from_the_tolerances(table, x_line_fits):
    """Over 12 tables drawn from the prior, the fitted values' errors against the truth
    in units of their posterior σ: mean z² = 1 ± 0.15 over the 504 (it is 1 for a
    calibrated posterior; the data-only σ are infinite, σ taken as the data's would make
    it far larger, σ ignoring the data's information far smaller where they inform). The
    prior check's p below 0.05 in at most 3 of 12 (a calibrated test: 5 %; P(≥ 4) = 0.2 %)."""
    z, small_p = [], 0
    for true, st, cal in x_line_fits:
        geo = [i for i, n in enumerate(cal.names) if not n.startswith("frame")]
        err = cal.value[geo] - truth_steps(table, true, [cal.names[i] for i in geo])
        z.append(err / cal.std[geo])
        small_p += jt.prior_check(cal.value, cal.covariance, cal.prior_sigma)[2] < 0.05
    z = np.concatenate(z)
    assert z.size == 12 * 42
    assert abs(np.mean(z**2) - 1) < 0.15, np.mean(z**2)
    assert small_p <= 3, small_p


def test_the_prior_check_s_false_alarm_rate_over_100_tables(table):
    """100 more tables built to their tolerances (drawn from the prior), each measured on
    its x line and fitted with the prior: the check's p below 0.05 in at most 10 of 100 (a
    check at the stated 5 % exceeds that with probability 1.2 %; one at 15 % stays within
    it with probability 0.10) and at least once (a check that never fires: P = 0.6 %);
    its p-values uniform (Kolmogorov–Smirnov p > 0.01); and the fitted values within
    their posterior σ of the truth over all of them (mean z² = 1 ± 0.06 over the 4,200: the
    tables' means scatter by 0.23, so ±0.06 is 2.6 standard errors; σ 10 % off would give
    0.83 or 1.21)."""
    from scipy.stats import binom, kstest

    assert binom.sf(10, 100, 0.05) < 0.015 and binom.cdf(10, 100, 0.15) < 0.11
    ps, z = [], []
    for seed in range(100, 200):
        true = perturb_table(table, seed=seed, joint_sigma=TOL.base_joints, zero_sigma=L0_SIGMA)
        cal = fit(setup(table, x_only(table, true, seed=seed), prior=TOL, compensated=True))
        ps.append(jt.prior_check(cal.value, cal.covariance, cal.prior_sigma)[2])
        geo = [i for i, n in enumerate(cal.names) if not n.startswith("frame")]
        err = cal.value[geo] - truth_steps(table, true, [cal.names[i] for i in geo])
        z.append(err / cal.std[geo])
    ps, z = np.array(ps), np.concatenate(z)
    assert 1 <= np.sum(ps < 0.05) <= 10, np.sort(ps)[:12]
    assert kstest(ps, "uniform").pvalue > 0.01, np.percentile(ps, [10, 25, 50, 75, 90])
    assert z.size == 4200 and abs(np.mean(z**2) - 1) < 0.06, np.mean(z**2)


def test_x_readings_alone_predict_other_poses_with_the_prior_not_without(table, x_line_fits):
    """The paper's measurement (x readings on the x line) fitted with every joint free:
    without the prior the joints move along what the data cannot determine (σ = inf), and
    the fitted table predicts a 6-D tracker's readings at 100 other poses worse than the
    nominal one; with it, at least as well as the nominal table (to 2 %), with every σ
    finite and the report saying what the tolerances set."""
    true, st, cal = x_line_fits[1]
    data = x_only(table, true, seed=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a table not physical, without
        free_fit = jt.calibrate(table, data, compensated=True)
    assert np.isinf(free_fit.std).sum() > 30
    other = jt.simulate(table, true, jt.plan_random(100, seed=7), jt.tracker6(), seed=8)
    nominal = np.sqrt(np.mean((other.measured[:, :3] - other.cmd_pose[:, :3]) ** 2))

    def predicted(c):
        rms = rms_of(c, table, other)
        return np.sqrt(np.mean([rms[k] ** 2 for k in "xyz"]))

    assert predicted(cal) < 1.02 * nominal, (predicted(cal), nominal)
    assert predicted(free_fit) > 3 * nominal, (predicted(free_fit), nominal)
    report = cal.report()
    assert "identifiable from these data and the prior" in report
    assert "σ = inf" not in report and "prior check" in report and "within them" in report


def test_a_table_beyond_its_tolerances_fails_the_prior_check(table):
    """Leg 2's zero length 1 mm off (20 of its 51 µm tolerance), seen on the x line: the
    fit cannot keep the geometry within the tolerances, and says so (p < 0.001)."""
    true = perturb_table(table, seed=30, joint_sigma=TOL.base_joints, zero_sigma=L0_SIGMA)
    true = jt.replace(true, zero_lengths=np.asarray(true.zero_lengths) + [0, 1.0, 0, 0, 0, 0])
    cal = jt.calibrate(table, x_only(table, true, seed=30), compensated=True, prior=TOL)
    x, expected, p = jt.prior_check(cal.value, cal.covariance, cal.prior_sigma)
    assert p < 1e-3 and x > 10 * expected, (x, expected, p)
    assert "beyond its tolerances" in cal.report()


def test_calibrate_cli_takes_the_prior(tmp_path, capsys):
    """`jaxtable calibrate --prior paper` on the bundled x-only file: every σ finite, the
    prior's lines in the report; a tolerance file works the same; a path that is not a
    file is refused with exit 2, nothing written."""
    data = Path(__file__).parent / "data" / "x_only_60_stops.csv"
    out = tmp_path / "out"
    args = ["calibrate", str(data), "--compensated", "--out", str(out), "--prior"]
    assert main(args + ["paper"]) == 0
    said = capsys.readouterr().out
    assert "prior (tolerances): 42 of the 45 fitted parameters" in said, said
    assert "σ = inf" not in said and "converged: True" in said
    tol = tmp_path / "tol.toml"
    jt.save_tolerances(jt.Tolerances(base_joints=0.02), tol)
    assert main(args + [str(tol)]) == 0
    assert "prior (tolerances)" in capsys.readouterr().out
    assert main(args[:-3] + ["--out", str(tmp_path / "no"), "--prior", "nope.toml"]) == 2
    assert "--prior: 'nope.toml' is neither 'paper' nor a tolerance file" in capsys.readouterr().err
    assert not (tmp_path / "no").exists()


@pytest.mark.slow
def test_mcmc_with_the_prior_agrees_with_the_map_posterior(table, x_line_fits):
    """emcee on the posterior with the prior's term (`posterior`), 2000 steps: the sampled
    σ of the 43 parameters within 15 % of the MAP fit's (median within 5 %)."""
    from jaxtable._calibration.posterior import posterior

    _, st, cal = x_line_fits[2]
    post = posterior(st, cal, n_steps=2000, progress=False)
    ratio = post.samples.std(0) / cal.std
    assert np.all(np.abs(ratio - 1) < 0.15) and abs(np.median(ratio) - 1) < 0.05, ratio
