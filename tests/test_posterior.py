"""emcee posterior of a calibration: agreement with the LM covariance on a well-conditioned
case (6-D tracker, random poses, L0 + instrument frame + target free), the short-chain warning,
unidentifiable directions held fixed, the corner plot and posterior-predictive bands.

One data shape and one fit are shared by every test (a calibration compiles in ~25 s)."""

import warnings

import emcee
import numpy as np
import pytest

import jaxtable as jt
from jaxtable._calibration.fit import fit, setup
from jaxtable._calibration.instruments import tracker6
from jaxtable._calibration.moves import SnookerMove
from jaxtable._calibration.posterior import posterior, predictive_bands
from jaxtable._calibration.simulate import perturb_table, plan_random, plan_x_line, simulate
from jaxtable._reports.posterior import corner_plot, plot_bands

N_POSES = 40


@pytest.fixture(scope="module")
def case(table):
    # only L0 errors in the truth: the model with L0 free is then exact (well specified)
    true = perturb_table(table, 11, joint_sigma=0.0, zero_sigma=0.05)
    data = simulate(table, true, plan_random(N_POSES, 11), tracker6(), seed=11)
    st = setup(table, data, ("zero_lengths",))
    cal = fit(st)
    assert cal.converged and not cal.unidentifiable
    return table, true, st, cal


@pytest.fixture(scope="module")
def chain(case):
    _, _, st, cal = case
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # 500 steps < 50 τ for 18 parameters
        return posterior(st, cal, n_steps=500, seed=1, progress=False)


def test_snooker_move_samples_a_standard_normal():
    """The corrected snooker move (with DE moves, as `posterior` uses them) leaves N(0, I)
    invariant: pooled std 1 within sampling error, where emcee 3.1.6's own DESnookerMove
    gives ~0.90 in 18-D."""
    d, w, n = 18, 38, 2000
    sampler = emcee.EnsembleSampler(
        w,
        d,
        lambda z: -0.5 * np.sum(z**2, axis=1),
        vectorize=True,
        moves=[(emcee.moves.DEMove(), 0.8), (SnookerMove(), 0.2)],
    )
    p0 = np.random.default_rng(0).normal(size=(w, d))
    sampler.run_mcmc(emcee.State(p0, random_state=np.random.RandomState(0).get_state()), n)
    x = sampler.get_chain(discard=400, flat=True)
    assert abs(x.std(0).mean() - 1.0) < 0.03
    assert np.all(np.abs(x.std(0) - 1.0) < 0.12)
    assert np.all(np.abs(x.mean(0)) < 0.2)


def test_posterior_matches_lm_covariance_and_truth(case, chain):
    table, true, st, cal = case
    res = chain
    assert res.names == cal.names and res.samples.shape[1] == len(cal.names)
    assert res.rank == len(cal.names) and res.identifiable.all() and not res.fixed_directions
    assert 0.15 < res.acceptance < 0.6
    # near-linear model: the posterior is the LM Gaussian (std within 20 %, mean within
    # a fraction of a σ)
    ratio = res.std / cal.std
    assert np.all(np.abs(ratio - 1) < 0.2), dict(zip(res.names, ratio.round(3)))
    assert np.all(np.abs(res.mean - cal.value) < 0.4 * cal.std)
    # and it contains the truth: L0 errors, frame and target zero in the simulation
    truth = np.zeros(len(res.names))
    dl = np.asarray(true.zero_lengths) - np.asarray(table.zero_lengths)
    for i in range(6):
        truth[res.names.index(f"zero_lengths[{i + 1}]")] = dl[i]
    assert np.all(np.abs(res.mean - truth) < 4 * res.std)
    assert res.samples.shape[0] >= 500 and res.burn > 0 and res.thin >= 1


def test_short_chain_warns_and_unidentifiable_directions_stay_fixed(case):
    _, _, st, cal = case
    # declare the two weakest directions "unidentifiable" (same fit, stricter threshold)
    sv = np.sort(cal.singular_values)
    cal2 = fit(st, identifiability_tol=float(np.sqrt(sv[1] * sv[2])))
    assert len(cal2.unidentifiable) == 2
    with pytest.warns(UserWarning, match="shorter than 50 autocorrelation times"):
        res = posterior(st, cal2, n_steps=60, seed=2, progress=False)
    assert res.short_chain and res.rank == len(cal2.names) - 2
    assert len(res.fixed_directions) == 2
    assert np.array_equal(np.isinf(res.std), np.isinf(cal2.std))
    # samples move only within the identifiable subspace: the range of the LM covariance
    # (computed with the fit's Jacobian), so their projection on its null space is constant
    w, v = np.linalg.eigh(cal2.covariance / np.outer(cal.std, cal.std))
    null = v[:, w < 1e-9 * w.max()] / cal.std[:, None]
    assert null.shape[1] == 2
    proj = (res.samples - cal2.value) @ null
    assert np.abs(proj).max() < 1e-8 * np.abs((res.samples - cal2.value) @ v[:, -1:]).max()
    with pytest.raises(ValueError, match="n_walkers"):
        posterior(st, cal, n_walkers=7, n_steps=20, progress=False)


def test_corner_plot_and_predictive_bands(case, chain, tmp_path):
    table, true, st, cal = case
    shown = corner_plot(chain, tmp_path / "corner.png", max_params=6)
    assert len(shown) == 6 and (tmp_path / "corner.png").stat().st_size > 10_000
    poses = plan_x_line(50.0, 200.0)
    bands = predictive_bands(st, chain, poses, n_samples=150)
    plot_bands(bands, tmp_path / "bands.png")
    assert (tmp_path / "bands.png").stat().st_size > 10_000
    assert bands.bands.shape == (3, len(poses), 6) and bands.failed == 0
    # the LM prediction (pose error: translation, rotation vector), recomputed with the
    # public forward kinematics
    cmd = jt.actuator_command(table, poses)
    lm = np.asarray(jt.pose_error(jt.forward(cal.table, cmd, nominal=table, guess=poses), poses))
    np.testing.assert_allclose(bands.lm, lm, atol=1e-9)
    assert np.all((bands.bands[0] <= lm) & (lm <= bands.bands[-1]))
    # the true pose error lies within the bands' spread of the median
    true_err = np.asarray(jt.pose_error(jt.forward(true, cmd, nominal=table, guess=poses), poses))
    half = (bands.bands[-1] - bands.bands[0]) / 2
    assert np.all(np.abs(true_err - bands.bands[1]) < 2.5 * half)
    # the bands are not degenerate: L0 errors of ~50 µm are known to a few µm
    assert np.all(half[:, :3].max(0) > 1e-4)


def test_predictive_bands_name_the_poses_the_fitted_table_cannot_reach(case, chain):
    """A forward solve of the fitted table that fails (here: one Newton step allowed from
    the commanded pose) is a KinematicsError naming the poses, as everywhere else, not a
    RuntimeError the command line would print as a traceback."""
    from jaxtable._errors import KinematicsError
    from jaxtable._forward import ForwardOptions

    table, true, st, cal = case
    poses = plan_x_line(100.0, 200.0)
    with pytest.raises(KinematicsError, match=r"failed at 5 of the 5 commanded pose\(s\)"):
        predictive_bands(st, chain, poses, n_samples=2, options=ForwardOptions(max_steps=1))
