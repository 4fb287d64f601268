"""Tolerance budgets: files, linear propagation identities, Monte Carlo cross-check."""

import jax.numpy as jnp
import numpy as np
import pytest
from conftest import quick_jit

from jaxtable._analysis.errormap import budget_one
from jaxtable._analysis.montecarlo import monte_carlo
from jaxtable._analysis.tolerances import (
    SOURCES,
    ToleranceFileError,
    Tolerances,
    load_tolerances,
    save_tolerances,
)

# eagerly, every op of the budget compiles on its own
budget = quick_jit(budget_one)


def test_default_is_the_papers_budget():
    t = Tolerances()
    assert (t.base_joints, t.platform_joints, t.lead_error, t.clearance) == (0.01, 0.01, 0.025, 0.1)
    assert t.sigma("lead_error") == pytest.approx(8.333e-5, rel=1e-3)
    assert t.sigma("clearance") == 0.05


def test_file_round_trip_and_partial_file(tmp_path):
    t = Tolerances(base_joints=0.02, clearance=0.0)
    save_tolerances(t, tmp_path / "t.toml")
    assert load_tolerances(tmp_path / "t.toml") == t
    (tmp_path / "p.toml").write_text("lead_error = 0.05\n")
    assert load_tolerances(tmp_path / "p.toml") == Tolerances(lead_error=0.05)


@pytest.mark.parametrize(
    "text, words",
    [
        ("base_joints = -0.01\n", ["'base_joints'", ">= 0"]),
        ("joint_wobble = 0.01\n", ["unknown error source", "'joint_wobble'"]),
        ("clearance = 'big'\n", ["'clearance'", "finite number"]),
        ("clearance = \n", ["not valid TOML"]),
    ],
)
def test_bad_tolerance_file_is_refused_by_name(tmp_path, text, words):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ToleranceFileError) as e:
        load_tolerances(path)
    for w in words:
        assert w in str(e.value)


def test_linear_identities(table):
    """First order, a joint-centre error moves the leg length by u·δ (variance σ² for three iid
    coordinates), exactly like an L0 error of the same σ; at home no travel means no lead
    error; the clearance acts as an L0 error of σ = w/2."""
    pose = jnp.asarray([-120.0, 80.0, 30.0, 0.05, -0.08, 0.1])
    std = np.asarray(budget(table, Tolerances().sigmas(), pose)[0])
    src = {s: std[k] for k, s in enumerate(SOURCES)}
    # exact for the rigid part; the passive term's own dependence on the joints adds ~1e-4
    np.testing.assert_allclose(src["base_joints"], src["zero_length"], rtol=1e-3)
    np.testing.assert_allclose(src["platform_joints"], src["zero_length"], rtol=1e-3)
    np.testing.assert_allclose(src["clearance"], 5 * src["zero_length"], rtol=1e-4)
    np.testing.assert_allclose(std[-1], np.sqrt((std[:-1] ** 2).sum(0)), rtol=1e-12)
    home = np.asarray(budget(table, Tolerances().sigmas(), jnp.zeros(6))[0])
    assert np.abs(home[SOURCES.index("lead_error")]).max() < 1e-15
    assert np.abs(home[SOURCES.index("zero_length")]).max() > 1e-3


def test_linear_matches_monte_carlo_at_paper_tolerances(table):
    """2000 realisations: the standard error of an estimated σ is ~1.6 %; accept 8 %."""
    poses = np.array(
        [[0.0] * 6, [-200.0, 0, 0, 0, 0, 0], [100.0, -100.0, -50.0, -0.13, -0.13, 0.17]]
    )
    err = monte_carlo(table, Tolerances(), poses, 2000, seed=3)
    lin = np.stack(
        [np.asarray(budget(table, Tolerances().sigmas(), jnp.asarray(p))[0][-1]) for p in poses]
    )
    np.testing.assert_allclose(err.std(0) / lin, 1.0, atol=0.08)
    assert np.all(np.abs(err.mean(0)) < 4 * lin / np.sqrt(2000))  # no bias beyond noise


def test_linear_breaks_down_near_the_singular_low_pose(table):
    """Platform 10 mm above the base plane (z = −652 mm): the legs lie almost flat, the
    Jacobian's condition number is ~46 and the z error is not the linear prediction: the
    Monte Carlo mean sits well below zero (linear theory: 0) and the spread is larger. Lower
    still (z = −655 mm), some realisations have no pose near the command at all."""
    pose = np.array([[0.0, 0.0, -652.0, 0.0, 0.0, 0.0]])
    std, _, cond, _ = budget(table, Tolerances().sigmas(), jnp.asarray(pose[0]))
    lin_z = float(std[-1][2])
    assert float(cond) > 40
    err = monte_carlo(table, Tolerances(), pose, 4000, seed=1)[:, 0, 2]
    assert err.mean() < -0.1 * lin_z  # ≈ 10 standard errors off the linear zero mean
    assert np.sqrt((err**2).mean()) > 1.04 * lin_z
    lower = monte_carlo(
        table,
        Tolerances(),
        np.array([[0.0, 0, -655.0, 0, 0, 0]]),
        4000,
        seed=1,
        allow_failures=True,
    )
    assert np.isnan(lower[:, 0, 0]).mean() > 0.01
    with pytest.raises(RuntimeError, match="Monte Carlo solves failed"):
        monte_carlo(table, Tolerances(), np.array([[0.0, 0, -655.0, 0, 0, 0]]), 4000, seed=1)
