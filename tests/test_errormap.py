"""Workspace error maps: grid layout, chunking, independent cross-checks, CLI."""

import jax
import numpy as np
import pytest
from conftest import compiled_programs, quick_jit, random_poses

import jaxtable as jt
from jaxtable._analysis.errormap import PoseList, _Histograms, error_map, workspace_slice
from jaxtable._analysis.sensitivities import pose_sensitivity
from jaxtable._analysis.tolerances import PARAMETER, SOURCES, Tolerances, budget_effects
from jaxtable.cli import main


def test_slice_layout():
    g = workspace_slice(("x", "yaw"), (3, 5), ranges=(100.0, 10.0), fixed=[0, 0, -20, 1, 0, 0])
    p = g.poses().reshape(3, 5, 6)
    np.testing.assert_allclose(p[:, 0, 0], [-100, 0, 100])
    np.testing.assert_allclose(np.rad2deg(p[0, :, 5]), [-10, -5, 0, 5, 10])
    np.testing.assert_allclose(p[..., 2], -20.0)
    np.testing.assert_allclose(p[..., 3], np.deg2rad(1.0))
    np.testing.assert_array_equal(g.poses(4, 9), g.poses()[4:9])
    with pytest.raises(ValueError, match="unknown pose DOF 'q'"):
        workspace_slice(("x", "q"))
    with pytest.raises(ValueError, match="repeated DOF"):
        workspace_slice(("x", "x"))
    for n in (1, 0, (3, 0), (3, 2.5), (3, 3, 3)):  # a line of one point sat at -range
        with pytest.raises(ValueError, match="whole number of at least 2"):
            workspace_slice(("x", "yaw"), n)
    assert workspace_slice(("x", "yaw"), (2, 3.0)).shape == (2, 3)


@pytest.fixture(scope="module")
def small_map(table):
    grid = workspace_slice(("x", "pitch"), (9, 7), fixed=[0, 20, 0, 0, 0, 5])
    return grid, error_map(table, Tolerances(), grid)


def test_chunking_does_not_change_results(table, small_map):
    grid, (emap, summary) = small_map
    emap2, summary2 = error_map(table, Tolerances(), grid, chunk=10)
    np.testing.assert_allclose(emap2.std, emap.std, rtol=1e-6)
    _, summary3 = error_map(table, Tolerances(), grid, keep=False, chunk=16)
    for name, v in summary["sources"].items():
        assert summary3["sources"][name] == pytest.approx(v, rel=1e-9)
    assert summary3["meets_target_uncompensated"] == summary["meets_target_uncompensated"]
    assert summary2["sources"]["total"]["trans_max_mm"] == pytest.approx(
        summary["sources"]["total"]["trans_max_mm"], rel=1e-12
    )
    assert emap.std.shape == (9, 7, len(SOURCES) + 1, 6)


def test_another_budget_runs_the_same_program_and_scales_sigma(table, small_map):
    """First order, every σ is linear in the tolerances: a budget scaled by 3 gives 3x each
    source's σ and the total, and the same spiral bias and condition number. It runs the
    program the default budget compiled (the σ are the kernel's arguments, not constants
    built into it): nothing is traced or lowered again."""
    grid, (emap, _) = small_map
    with compiled_programs("jaxpr_to_mlir_module") as lowered:
        emap3, _ = error_map(table, Tolerances().scaled(3.0), grid)
    assert not [name for name in lowered if "budget_row" in name], lowered
    np.testing.assert_allclose(emap3.std, 3.0 * emap.std, rtol=1e-6)  # the map keeps float32
    np.testing.assert_array_equal(emap3.bias, emap.bias)
    np.testing.assert_array_equal(emap3.cond, emap.cond)


def test_histogram_bins_by_arithmetic_equal_searchsorted():
    """The kernel's bin index (log arithmetic) is numpy's searchsorted on the bin edges: equal
    away from an edge, at most one bin off exactly at one; 0, NaN and out-of-range values
    land in the end bins."""
    h = _Histograms((1,))
    rng = np.random.default_rng(3)
    x = 10.0 ** rng.uniform(-10, 4, 200_000)
    k = np.asarray(_Histograms.bin_index(x))  # (a draw within rounding of an edge: p ~ 1e-7)
    np.testing.assert_array_equal(k, np.searchsorted(h.edges, x))
    k_edges = np.asarray(_Histograms.bin_index(h.edges))
    assert np.abs(k_edges - np.arange(len(h.edges))).max() <= 1
    ends = np.asarray(_Histograms.bin_index(np.array([0.0, np.nan, 1e-12, 1e6])))
    np.testing.assert_array_equal(ends, [0, h.BINS + 1, 0, h.BINS + 1])


def test_histograms_count_the_counted_rows_only():
    """A chunk's slots (`_Histograms.slots`, as the kernel writes them) counted by `add`:
    each histogram holds the bins of the rows marked counted and nothing of the others, and
    the maxima are those of the counted rows (the kernel gives the others' values as 0)."""
    rng = np.random.default_rng(5)
    x = 10.0 ** rng.uniform(-8, 2, (500, 2, 3))
    counted = rng.random(500) < 0.6
    slots = np.asarray(quick_jit(jax.vmap(_Histograms.slots))(x, counted))
    h = _Histograms((2, 3))
    h.add(np.where(counted[:, None, None], x, 0.0), slots)
    for i in range(2):
        for j in range(3):
            want = np.bincount(np.searchsorted(h.edges, x[counted, i, j]), minlength=h.BINS + 2)
            np.testing.assert_array_equal(h.counts[i, j], want)
            assert h.max[i, j] == x[counted, i, j].max()
    assert h.counts.sum() == 6 * counted.sum()


def test_streamed_summary_equals_the_kept_map(table):
    """The summary counted from the kernel's bins (in chunks) against numpy statistics of the
    kept per-pose map, over reachable poses only (a third of the poses are out of reach)."""
    poses = random_poses(3000, seed=8)
    poses[::3] *= 3.0
    emap, summary = error_map(table, Tolerances(), PoseList(poses), chunk=512)
    ok = emap.reachable
    assert 0 < ok.sum() < len(ok) and summary["reachable"] == ok.sum()
    names = list(SOURCES) + ["total", "total (spiral uncompensated)"]
    t = np.column_stack([emap.translation(True)[ok], emap.translation(False)[ok, -1]])
    r = np.column_stack([emap.rotation(True)[ok], emap.rotation(False)[ok, -1]]) * 206264.806
    edges = np.geomspace(1e-9, 1e3, 3001)  # the summary's log bins: 1e-9..1e3, 3000 bins

    def p95_of_bins(x):  # upper edge of the bin holding the 95th percentile
        counts = np.bincount(np.searchsorted(edges, x), minlength=3002)
        k = np.searchsorted(np.cumsum(counts), 0.95 * len(x))
        return edges[min(max(k, 1), 3000)]

    for k, name in enumerate(names):
        got = summary["sources"][name]
        for x, key in ((t[:, k], "trans"), (r[:, k], "rot")):
            unit = "mm" if key == "trans" else "arcsec"
            assert got[f"{key}_max_{unit}"] == pytest.approx(x.max(), rel=1e-6)  # map: float32
            p95 = got[f"{key}_p95_{unit}"]
            assert p95 == pytest.approx(p95_of_bins(x.astype(float)), rel=1e-12)
            q = np.percentile(x, [94, 96])  # and it is a 95th percentile, to a bin's width
            assert q[0] <= p95 <= q[1] * edges[1] / edges[0]
    for compensated, key in ((True, "compensated"), (False, "uncompensated")):
        frac = np.mean(emap.target_margin(compensated)[ok] <= 0.2)
        assert summary[f"meets_target_{key}"] == pytest.approx(frac, abs=1.5 / ok.sum())


def test_std_matches_general_sensitivity_path(table, small_map):
    """σ per source from the closed-form kernel = σ·‖row of dq/dθ‖ from the general
    autodiff path (pose_sensitivity), source by source: one call for every parameter, each
    source's columns picked by the names it returns."""
    grid, (emap, _) = small_map
    poses = grid.poses()[::7]
    eff = budget_effects(table)
    tol = Tolerances()
    wrt = tuple(dict.fromkeys(PARAMETER[src] for src in SOURCES))
    J, names = pose_sensitivity(table, poses, wrt=wrt, effects=eff, rotation_vector=True)
    J = np.asarray(J)
    for k, src in enumerate(SOURCES):
        cols = [j for j, name in enumerate(names) if name.split("[")[0] == PARAMETER[src]]
        assert len(cols) == (18 if "joints" in src else 6)
        std = tol.sigma(src) * np.sqrt((J[..., cols] ** 2).sum(-1))
        np.testing.assert_allclose(
            emap.std.reshape(-1, len(SOURCES) + 1, 6)[::7, k], std, rtol=1e-5, atol=1e-12
        )


def test_reachable_cond_and_bias_against_independent_truth(table):
    poses = np.array(
        [[-200.0, 0, 0, 0, 0, 0], [0, 0, 0, np.deg2rad(40), 0, 0], [50, -60, 20, 0.05, 0.1, -0.2]]
    )
    emap, _ = error_map(table, Tolerances(), PoseList(poses))
    np.testing.assert_array_equal(emap.reachable, np.asarray(jt.reachable(table, poses)))
    # condition number: numpy on the Jacobian of the actuator-side length (angles scaled)
    from jaxtable import _kinematics as kin

    r = float(np.mean(np.linalg.norm(np.asarray(table.platform_joints), axis=1)))
    jac = quick_jit(
        jax.jacfwd(lambda q: kin.leg_lengths(table, q) - kin.spiral_extension(table, q))
    )
    for k, p in enumerate(poses):
        J = np.array(jac(p))
        J[:, 3:] /= r
        assert emap.cond[k] == pytest.approx(np.linalg.cond(J), rel=1e-6)  # kept as float32
    # spiral bias: linearised; exact forward kinematics of the uncompensated command
    exact = np.asarray(jt.forward(table, jt.actuator_command(table, poses[:1], compensated=False)))
    err = exact[0] - poses[0]
    np.testing.assert_allclose(emap.bias[0, :3], err[:3], atol=0.02 * np.abs(err[:3]).max())


def test_map_without_condition_number_keeps_every_other_figure(table):
    poses = random_poses(300, seed=21)
    full, s_full = error_map(table, Tolerances(), PoseList(poses))
    lean, s_lean = error_map(table, Tolerances(), PoseList(poses), cond=False)
    np.testing.assert_array_equal(lean.std, full.std)
    np.testing.assert_array_equal(lean.bias, full.bias)
    np.testing.assert_array_equal(lean.reachable, full.reachable)
    assert np.isnan(lean.cond).all() and np.isfinite(full.cond).all()
    assert np.isnan(s_lean["cond_max"]) and s_full["cond_max"] > 1
    assert s_lean["sources"] == s_full["sources"]


def test_map_cli_writes_report_and_refuses_bad_tolerances(tmp_path, capsys):
    assert (
        main(["map", "--n", "9", "--slice", "roll,yaw", "--fixed", "z=-50", "--out", str(tmp_path)])
        == 0
    )
    for name in ("map.md", "map_roll_yaw.png", "error_x_stroke.png", "error_budget.png"):
        assert (tmp_path / name).stat().st_size > 500
    text = (tmp_path / "map.md").read_text()
    assert "81 reachable of 81 poses" in text and "| clearance |" in text
    bad = tmp_path / "tol.toml"
    bad.write_text("clearance = -1.0\n")
    assert main(["map", "--tolerances", str(bad), "--out", str(tmp_path)]) == 2
    assert "'clearance' must be >= 0" in capsys.readouterr().err
    # a slice with no reachable pose (z = 900 mm), a slice of one point: refused, nothing
    # written (it wrote a report of zeros and NaNs; the empty grid stopped with a traceback)
    none = tmp_path / "none"
    assert main(["map", "--n", "9", "--fixed", "z=900", "--out", str(none)]) == 2
    assert "none of the 81 poses of the x-y slice (z=900) is reachable" in capsys.readouterr().err
    with pytest.raises(SystemExit) as stop:  # argparse's refusal
        main(["map", "--n", "1", "--out", str(none)])
    assert stop.value.code == 2 and "argument --n: 1 is below the least value, 2" in (
        capsys.readouterr().err
    )
    assert not none.exists()
    with pytest.raises(ValueError, match="no poses"):
        error_map(jt.reference_table(), grid=np.zeros((0, 6)))
