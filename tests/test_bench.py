"""The benchmark's baselines compute the same thing as jaxtable, and its machine-limit count
matches the formulation (no timing is asserted anywhere)."""

import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import random_poses

import jaxtable as jt

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout's benchmarks/

from benchmarks.baselines import (  # noqa: E402
    numpy_command,
    numpy_design_criteria,
    numpy_error_map,
    scipy_forward,
)
from benchmarks.bench import hlo_op_counts, kernel_op_counts, machine_limit  # noqa: E402


def test_numpy_baseline_equals_the_compensated_command(table):
    poses = random_poses(200, seed=5)
    np.testing.assert_allclose(
        numpy_command(table, poses), np.asarray(jt.actuator_command(table, poses)), atol=1e-9
    )


def test_numpy_error_map_baseline_equals_the_error_map(table):
    """The benchmark's numpy error map (central differences of the numpy model, np.linalg
    inv and cond) against `jt.error_map` at random poses up to 1.5× the workspace box: every
    source's σ, the total, the uncompensated bias and the condition number, to the kept
    map's float32 rounding."""
    from jaxtable._forward import platform_radius

    poses = random_poses(300, seed=7) * 1.5
    tol = jt.Tolerances()
    sigmas = np.array(tol.sigmas())
    std, bias, cond = numpy_error_map(table, sigmas, poses, float(platform_radius(table)))
    m, _ = jt.error_map(table, tol, poses)
    assert std.shape == m.std.shape and bias.shape == m.bias.shape
    np.testing.assert_allclose(std, m.std, rtol=1e-6)
    np.testing.assert_allclose(bias, m.bias, rtol=1e-6, atol=1e-6 * np.abs(m.bias).max())
    np.testing.assert_allclose(cond, m.cond, rtol=1e-6)


def test_scipy_baseline_recovers_the_pose(table):
    poses = random_poses(3, seed=6)
    cmd = np.asarray(jt.actuator_command(table, poses))
    np.testing.assert_allclose(scipy_forward(table, cmd), poses, atol=1e-8)


def test_kernel_op_counts_match_the_formulation(table):
    c = kernel_op_counts(table)
    # per pose: sin and cos of 3 angles; per leg one sqrt (|l|) and one atan2 (the twist)
    assert (c["sin"], c["cos"], c["sqrt"], c["atan2"]) == (3, 3, 6, 6)
    assert 100 < c["arith"] < 2000
    rates = {k: 1e9 for k in c}
    assert machine_limit(c, rates) == pytest.approx(1e9 / sum(c.values()))


def test_hlo_op_counts_of_a_reduction_and_a_dot():
    """Hand counts: Σ x_k² over 6 entries is 6 multiplies and 5 adds; a 6×6 matrix times a
    6-vector is 36 multiply-adds (72 ops); the batch is the leading dimension."""
    N = 512
    f = jax.jit(jax.vmap(lambda x: jnp.sum(x * x)))
    assert hlo_op_counts(f.lower(jnp.zeros((N, 6))).compile().as_text(), N)["arith"] == 11
    g = jax.jit(jax.vmap(lambda a, v: a @ v))
    text = g.lower(jnp.ones((N, 6, 6)), jnp.ones((N, 6))).compile().as_text()
    assert hlo_op_counts(text, N)["arith"] == 72


def test_hlo_op_counts_of_a_loop_count_its_body_per_trip():
    """y ← y² + x, 17 and 40 times: a multiply and an add per trip (34 and 80 ops a pose);
    the loop's counter and condition are scalars, not counted per pose."""
    N = 512
    for n in (17, 40):
        f = jax.jit(jax.vmap(lambda x, n=n: jax.lax.fori_loop(0, n, lambda i, y: y * y + x, x)))
        text = f.lower(jnp.zeros(N)).compile().as_text()
        assert " while(" in text  # a loop, not unrolled by the compiler
        assert hlo_op_counts(text, N)["arith"] == 2 * n


@pytest.mark.slow
def test_bench_cli_quick_writes_every_figure(tmp_path):
    from jaxtable.cli import main

    assert main(["bench", "--quick", "--out", str(tmp_path)]) == 0
    r = json.loads((tmp_path / "benchmark.json").read_text())
    assert {
        "ik",
        "ik_limit",
        "fk",
        "fk_limit",
        "fk_scipy",
        "error_map",
        "sensitivity",
        "calibration",
        "latency",
        "map",
        "error_map_big",
    } <= set(r)
    assert r["error_map_big"]["poses"] == 10**4 and r["error_map_big"]["cond_max"] > 1
    assert all("numpy_per_s" in x for x in r["ik"])
    assert all(x["converged"] == 1.0 for x in r["fk"])
    assert {"mean_steps", "limit_per_s", "fraction"} <= set(r["fk_limit"])
    assert {"limit_per_s", "budget_only_limit_per_s"} <= set(r["error_map"])
    assert (tmp_path / "benchmark.md").read_text().count("|") > 50


def test_numpy_design_baseline_equals_the_design_criteria(table):
    design = jt.Design(jt.SymmetricDesign.from_table(table), jt.hardware_for(table))
    poses = jt.design_poses(None, n_sweep=3, n_random=20, box=2)
    hw = design.hardware
    ours = jt.assess_design(design, workspace=poses).values
    base = numpy_design_criteria(
        design.table(),
        float(hw.leg_stiffness[0]),
        float(hw.moving_mass(design.table())),
        float(hw.acceleration),
        float(hw.characteristic_length),
        np.asarray(hw.inertia),
        poses,
    )
    for k, v in base.items():
        assert ours[k] == pytest.approx(v, rel=1e-9), k
