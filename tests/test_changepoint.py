"""A step in time within a session: the instrument moved, or the legs' zeros moved (the
controller homed again), part-way through a recording that the file calls one session."""

import dataclasses
import json

import numpy as np
import pytest
from conftest import compiled_programs
from scipy.stats import binom, chi2, kstest

import jaxtable as jt
from jaxtable._calibration.fit import fit_screened
from jaxtable._discovery.changepoint import split_session, step_scan
from jaxtable._params import GEOMETRY
from jaxtable.cli import main

N, AT = 100, 60  # stops; the step comes before row index AT (row AT + 1 of the file)
FRAME_STEP = (0.03, 0.0, -0.02, 0.0, 0.0, np.deg2rad(5.0 / 3600.0))  # mm, rad


def _recording(seed, frame_step=None, zero_step=None, n=N, at=AT):
    """One session of `n` stops of a 6-D tracker on a table with geometric errors and no
    other effect; from row index `at` on, the tracker frame moved by `frame_step` or the
    legs' zeros by `zero_step` (mm)."""
    table = jt.reference_table()
    true = jt.perturb_table(table, seed, joint_sigma=0.010, zero_sigma=0.050)
    plan = jt.plan_random(n, seed)
    later = true
    if zero_step is not None:
        later = jt.replace(true, zero_lengths=np.asarray(true.zero_lengths) + zero_step)
    frame = np.zeros(6) if frame_step is None else np.asarray(frame_step)
    parts = [
        jt.simulate(
            table,
            t,
            plan[rows],
            jt.tracker6(),
            effects={},
            compensated=True,
            seed=seed + 7 * k,
            frame=f,
        )  # fmt: skip
        for k, (rows, t, f) in enumerate(
            ((np.arange(at), true, np.zeros(6)), (np.arange(at, n), later, frame))
        )
    ]
    data = jt.Measurements(
        *(np.concatenate([getattr(p, f) for p in parts]) for f in ("cmd_pose", "measured")),
        cmd_lengths=np.concatenate([p.cmd_lengths for p in parts]),
        sigma=np.concatenate([p.sigma for p in parts]),
    )
    return table, data


def _fit(table, data):
    return fit_screened(table, data, GEOMETRY, effects={}, outliers="keep")


def test_an_instrument_moved_part_way_is_found_where_it_moved():
    """The tracker knocked before row 61 (x +30 µm, z −20 µm, yaw +5″): the scan names row
    61 and the instrument frame, and its linearised step is the one an exact refit with
    rows 61… as a session of their own finds (the difference of the two sessions' frames)
    to a tenth of its standard deviation."""
    table, data = _recording(1, frame_step=FRAME_STEP)
    st, cal = _fit(table, data)
    step = step_scan(cal, st)
    assert step.found and step.row == AT + 1 and step.kind == "instrument frame", step.words()
    assert step.session == "1" and step.p_value < 0.002
    _, split = _fit(table, split_session(data, AT, "1@61"))
    frames = np.asarray(split.frame)
    np.testing.assert_array_less(np.abs(step.shift - (frames[1] - frames[0])), 0.1 * step.shift_std)
    assert abs(step.shift[0] - 0.03) < 0.005  # x, mm: what was planted
    assert "the residuals step at row 61 (session 1): the instrument moved" in step.words()


def test_a_large_step_is_placed_where_it_is():
    """A knock of 150 µm, 30 times the noise: the row and kind found. The scan's statistic,
    −log of the χ² tail, keeps growing with Δχ² past where the tail underflows (Δχ² beyond
    ~1,400: a long log; with σ estimated from the residuals a step's Δχ² stays under the
    fit's degrees of freedom), where scipy.stats' `logsf` returns inf and the first row of
    a tie would win; it matches the ufunc where that is representable (1e-10 relative)."""
    from scipy.special import chdtrc

    from jaxtable._discovery.changepoint import _log_sf

    table, data = _recording(5, frame_step=5 * np.asarray(FRAME_STEP))
    st, cal = _fit(table, data)
    step = step_scan(cal, st, draws=100)
    assert step.row == AT + 1 and step.kind == "instrument frame"
    d, q = np.array([900.0, 1250.0, 1300.0]), np.array([6, 1, 5])
    np.testing.assert_allclose(_log_sf(d, q), -np.log(chdtrc(q, d)), rtol=1e-10)
    big = _log_sf(np.array([1400.0, 1500.0, 1e4, 1e5]), np.full(4, 6))
    assert np.all(np.isfinite(big)) and np.all(np.diff(big) > 0)


def test_calibrate_names_the_step_where_its_residuals_show_structure():
    """`calibrate` on the knocked recording: the residuals show structure, so the
    gross-error screen does not run, and the report names the step and what to do."""
    table, data = _recording(1, frame_step=FRAME_STEP)
    cal = jt.calibrate(table, data, effects={})
    assert cal.set_aside == [] and cal.screen_skipped
    assert cal.step is not None and cal.step.row == AT + 1
    assert "mark rows 61… of session 1 as a session of their own" in cal.report()
    clean = jt.calibrate(table, _recording(1)[1], effects={})
    assert clean.step is None and "the residuals step" not in clean.report()


def test_legs_homed_again_part_way_are_found_as_a_step_of_their_zeros():
    """The six zero lengths moved by 10–30 µm before row 61 (the controller homed again):
    the scan names row 61 and the leg zeros, each leg's step within 4 of its (high-side)
    standard deviations of the planted one."""
    zero_step = np.array([0.02, -0.01, 0.03, -0.025, 0.015, -0.02])
    table, data = _recording(2, zero_step=zero_step)
    st, cal = _fit(table, data)
    step = step_scan(cal, st)
    assert step.found and step.row == AT + 1 and step.kind == "leg zeros", step.words()
    assert np.all(np.abs(step.shift - zero_step) < 4 * step.shift_std), (step.shift, zero_step)
    assert step.names == tuple(f"zero_lengths[{i}]" for i in range(1, 7))


def test_the_scan_s_false_alarm_rate_holds_over_100_clean_recordings():
    """No step: over 100 recordings of 40 stops the scan's p-values (largest statistic over
    20 rows and two kinds, its Monte Carlo null law) are uniform (Kolmogorov–Smirnov), and
    at most the binomial 99th percentile at 5 % (11) fall under 0.05. The largest Δχ²
    over rows and kinds taken at its nominal χ² level instead (no correction for the
    search) falls under 0.05 in 23 of them: it would fail the bound."""
    p, naive = [], 0
    for seed in range(100):
        table, data = _recording(100 + seed, n=40, at=20)
        st, cal = _fit(table, data)
        step = step_scan(cal, st, alpha=0.05, draws=200, seed=seed)
        p.append(step.p_value)
        naive += bool(chi2.sf(step.delta_chi2, step.dof) < 0.05)
    p = np.asarray(p)
    assert np.sum(p < 0.05) <= binom.ppf(0.99, 100, 0.05), np.sort(p)[:15]
    assert kstest(p, "uniform").pvalue > 1e-3, np.sort(p)
    bound = binom.ppf(0.99, 100, 0.05)
    assert naive > bound, naive


def test_split_session_names_the_rows_after_the_step():
    table, data = _recording(3, n=30, at=10)
    data = dataclasses.replace(data, session=np.array(["A"] * 20 + ["B"] * 10))
    out = split_session(data, 12, "A@13")
    assert out.session.tolist() == ["A"] * 12 + ["A@13"] * 8 + ["B"] * 10
    assert data.session.tolist() == ["A"] * 20 + ["B"] * 10  # a copy
    with pytest.raises(ValueError, match="already in use"):
        split_session(out, 3, "B")


def test_diagnose_splits_the_session_and_finds_the_model_of_the_whole_file(tmp_path):
    """The tracker knocked part-way through a recording of a table with the passive spiral
    (150 stops, temperature rising over the run): with one session the diagnosis added
    thermal (the step looks like a drift in time) and left structure unexplained; with the
    step found it diagnoses the rows after it as a session of their own and selects the
    spiral alone, no structure left, the held-out RMS lower; the JSON names the split. The
    two diagnoses share one compiled fit program."""
    table = jt.reference_table()
    rng = np.random.default_rng(7)
    true = jt.perturb_table(table, 7, joint_sigma=0.010, zero_sigma=0.050)
    n, at = 150, 90
    plan = jt.plan_random(n, 7)
    temperature = 20 + 10 * np.arange(n) / n + rng.normal(0, 0.2, n)
    eff = {"spiral": jt.Spiral(12.7)}
    parts = [
        jt.simulate(
            table,
            true,
            plan[rows],
            jt.tracker6(),
            effects=eff,
            compensated=False,
            seed=7 + k,
            frame=f,
            temperature=temperature[rows],
        )  # fmt: skip
        for k, (rows, f) in enumerate(
            ((np.arange(at), np.zeros(6)), (np.arange(at, n), FRAME_STEP))
        )
    ]
    data = jt.Measurements(
        *(np.concatenate([getattr(p, f) for p in parts]) for f in ("cmd_pose", "measured")),
        cmd_lengths=np.concatenate([p.cmd_lengths for p in parts]),
        sigma=np.concatenate([p.sigma for p in parts]),
        temperature=temperature,
    )
    lines = []
    with compiled_programs() as compiles:
        diag = jt.diagnose(table, data, log=lines.append, flexible=False, discover=False)
    # the diagnosis again with two sessions runs the one-session diagnosis's fit program
    assert compiles.count("jit(_block_jacobian)") <= 1, compiles
    assert any("diagnosing again with rows 91… of session 1 as session '1@91'" in x for x in lines)
    assert [s.step.row for s in diag.split_sessions] == [91]
    split = diag.split_sessions[0]
    assert split.step.kind == "instrument frame" and split.label == "1@91"
    assert diag.selected == ["spiral"] and not diag.unexplained, (diag.selected, lines)
    assert split.heldout_rms_after < split.heldout_rms_before
    assert diag.data.sessions == ["1", "1@91"]
    from jaxtable._reports.diagnose import write_report

    write_report(diag, tmp_path, "knocked.csv", tmp_path / "d.json")
    doc = json.loads((tmp_path / "d.json").read_text())["sessions_split"]
    assert doc[0]["row"] == 91 and doc[0]["kind"] == "instrument frame" and doc[0]["found"]
    assert abs(doc[0]["shift"]["frame[1].x"] - 0.03) < 0.005
    text = (tmp_path / "report.md").read_text()
    assert "**Session split at a step in time**" in text and "session '1@91'" in text
    assert (
        "![session_steps](session_steps.png)" in text and (tmp_path / "session_steps.png").exists()
    )
    model = jt.load_fitted_model(tmp_path / "calibrated_table.toml")  # the new session's frame
    assert set(model.instrument.frames) == {"1", "1@91"}
    rows, chi2 = split.step.profile["instrument frame"]
    assert rows[np.argmax(chi2)] == 91 and np.isclose(chi2.max(), split.step.delta_chi2)


def test_the_command_line_keeps_the_sessions_when_asked(monkeypatch, tmp_path):
    """`--keep-sessions` reaches `diagnose` as session_steps="keep"; "split" without it."""
    import jaxtable._discovery.diagnose as module

    seen = []

    def fake(*args, **kw):
        seen.append(kw["session_steps"])
        raise ValueError("stop here")

    monkeypatch.setattr(module, "diagnose", fake)
    for extra in ([], ["--keep-sessions"]):
        assert main(["diagnose", "--out", str(tmp_path), *extra]) != 0  # refused: stop here
    assert seen == ["split", "keep"]


def test_diagnose_finds_legs_homed_again_and_selects_rehoming():
    """The legs' zeros moved by 10–30 µm before row 61 of 100 (one session in the file):
    the diagnosis splits the session there, as a step of the leg zeros, then selects the
    library's rehoming effect for the new session (its offsets within 4 sd of the
    planted step) and leaves no structure."""
    zero_step = np.array([0.02, -0.01, 0.03, -0.025, 0.015, -0.02])
    table, data = _recording(2, zero_step=zero_step)
    diag = jt.diagnose(table, data, base=(), log=lambda _: None, flexible=False, discover=False)
    assert [(s.step.row, s.step.kind) for s in diag.split_sessions] == [(61, "leg zeros")]
    assert "rehoming" in diag.selected and not diag.unexplained, diag.selected
    value, std = diag.effect_params("rehoming")["offsets"]
    assert np.all(np.abs(np.ravel(value) - zero_step) < 4 * np.ravel(std)), (value, zero_step)


def _warming(tau: float | None, n: int = 100):
    """A table whose legs grow with temperature (11.5e-6 /K, no other effect), the
    temperature rising 10 K over the run: linearly (`tau` None) or as a warm-up
    20 + 10 (1 − exp(−row / tau))."""
    table = jt.reference_table()
    true = jt.perturb_table(table, 4, joint_sigma=0.010, zero_sigma=0.050)
    rows = np.arange(n)
    rise = rows / n if tau is None else 1 - np.exp(-rows / tau)
    temperature = 20 + 10 * rise + np.random.default_rng(4).normal(0, 0.2, n)
    data = jt.simulate(table, true, jt.plan_random(n, 4), jt.tracker6(),
                       effects={"thermal": jt.Thermal(np.full(6, 11.5e-6))}, compensated=True,
                       seed=4, temperature=temperature)  # fmt: skip
    return table, data


def test_a_drift_across_a_pause_is_a_drift_on_the_log_s_clock():
    """Aluminium legs (23e-6 /K) warming 20 K linearly in time over two 50-minute runs with
    a 50-minute pause between them (one session, the `time` column logged): in row order
    the pause is a jump in the drift, which a step at the pause nearly matches; on the
    clock the drift is a line, takes out more than the step, and no step is found."""
    table = jt.reference_table()
    true = jt.perturb_table(table, 4, joint_sigma=0.010, zero_sigma=0.050)
    rows = np.arange(100)
    clock = 60.0 * rows + np.where(rows >= 50, 3000.0, 0.0)
    temperature = 20 + 20 * clock / clock[-1] + np.random.default_rng(5).normal(0, 0.2, 100)
    data = jt.simulate(table, true, jt.plan_random(100, 5), jt.tracker6(),
                       effects={"thermal": jt.Thermal(np.full(6, 23e-6))}, compensated=True,
                       seed=5, temperature=temperature, time=clock)  # fmt: skip
    timed = step_scan(*_fit(table, data)[::-1])
    assert timed.p_value < 0.01 and timed.row == 51 and timed.kind == "leg zeros"
    assert timed.drift_chi2 > 1.04 * timed.delta_chi2 and not timed.found, timed.words()
    ordered = step_scan(*_fit(table, dataclasses.replace(data, time=None))[::-1])
    assert ordered.row == 51 and ordered.delta_chi2 == pytest.approx(timed.delta_chi2)
    assert ordered.drift_chi2 < timed.drift_chi2 - 0.04 * timed.delta_chi2


def test_a_drift_is_not_taken_for_a_step():
    """Thermal growth the geometric model misses, the temperature rising linearly: a step
    part-way takes out much of it (p < 0.01), but a linear drift of the same parameters
    takes out more, so no step is found. A warm-up (the temperature rising fast, then
    levelling off) is better fitted by a step than by a linear drift: `calibrate` names no
    step (the fit with the rows after it as a session of their own still shows structure),
    and `diagnose` without the thermal effect in its library splits the session twice,
    finds structure still unexplained, and keeps the file's sessions."""
    table, data = _warming(None)
    st, cal = _fit(table, data)
    step = step_scan(cal, st)
    assert step.p_value < 0.01 and step.drift_chi2 > step.delta_chi2 and not step.found
    assert step.words().startswith("a drift rather than a step")
    table, data = _warming(10.0)
    st, cal = _fit(table, data)
    assert step_scan(cal, st).found  # a step takes out more than a linear drift
    assert jt.calibrate(table, data, effects={}).step is None
    lines = []
    diag = jt.diagnose(table, data, log=lines.append, library=[], discover=False, flexible=False)
    assert sum("diagnosing again with rows" in x for x in lines) == 2, lines
    assert any("leave structure unexplained: not steps" in x for x in lines)
    assert diag.split_sessions == [] and diag.unexplained and diag.data.sessions == ["1"]


class _LegDrift(jt.AbstractEffect):
    """Leg lengths drifting linearly over the run (the file's clock, 0..1): c_i t, mm."""

    c: np.ndarray

    def __call__(self, table, pose, s, ctx=None):
        return self.c * ctx.time


def _drifting(instrument: bool, n: int = 150, seed: int = 5):
    """`n` stops of a table with geometric errors read by a 6-D tracker 1 m away: the
    tracker turning 20″ about its vertical over the run, or the legs drifting by 30, −20,
    10, 25, −15, 5 µm."""
    table = jt.reference_table()
    true = jt.perturb_table(table, seed)
    c = np.array([30.0, -20.0, 10.0, 25.0, -15.0, 5.0]) * 1e-3
    effects = {} if instrument else {"drift": _LegDrift(c)}
    d = jt.simulate(table, true, jt.plan_random(n, seed + 1), jt.tracker6(), seed=seed + 2,
                    frame=(300.0, -200.0, 800.0, 0.1, 0.2, 0.3), effects=effects)  # fmt: skip
    m = d.measured.copy()
    if instrument:  # the frame turns about the tracker's z: positions rotate, the yaw adds
        th = np.deg2rad(20.0 / 3600) * np.linspace(0, 1, n)
        x, y = d.measured[:, 0], d.measured[:, 1]
        m[:, 0], m[:, 1] = np.cos(th) * x - np.sin(th) * y, np.sin(th) * x + np.cos(th) * y
        m[:, 5] += th
    return table, dataclasses.replace(d, measured=m, sigma=None)


def test_a_drift_in_time_is_told_the_instrument_s_or_the_legs():
    """A drift of the instrument's frame and a drift of the legs' zeros are different
    functions of the pose. The drift's Δχ² of each kind (linearised at the fit) equals the
    χ² that a least-squares refit with the drift's columns added to the fit's Jacobian
    takes out (numpy's lstsq, to 1e-4: the fit converged to ~1e-5 of it). `diagnose`: the
    legs drifting are discovered as the drift term `t`, named the legs'; the tracker
    turning 20″ over the run is named the instrument's ("would move the table off") and its
    frame's drift is fitted in place of the term, a nuisance the model does not carry: the
    yaw's drift is the turn, and the frame's translation turns with it, by 20″ × its
    lever about the tracker's z (x −20″ × (−200 mm) = +19.4 µm, y 20″ × 300 mm = +29.1
    µm), each within 3.5 σ."""
    from jaxtable._discovery.changepoint import _kinds
    from jaxtable._discovery.structure import whitened

    table, d = _drifting(True)
    st, cal = fit_screened(table, d, GEOMETRY, effects={}, outliers="keep")
    w = whitened(cal, st)
    J = np.asarray(cal.jacobian) * w.factor.reshape(-1, 1)
    keep = w.mask.reshape(-1)
    e = w.e.reshape(-1)[keep]

    def left(A):
        return float(np.sum((e - A @ np.linalg.lstsq(A, e, rcond=None)[0]) ** 2))

    kinds = _kinds(cal, st, w, 2)
    assert sorted(kd.kind for kd in kinds) == ["instrument frame", "leg zeros"]
    for kd in kinds:
        ramp = np.zeros((len(w.mask), 6, kd.ramp.shape[-1]))
        ramp[kd.rows] = kd.ramp
        both = np.hstack([J, ramp.reshape(len(keep), -1)])[keep]
        assert kd.drift_chi2(w.e) == pytest.approx(left(J[keep]) - left(both), rel=1e-4)
    table, d = _drifting(False)
    diag = jt.diagnose(table, d, library=[], flexible=False, log=lambda _: None)
    drift = [f for f in diag.discovered if f.candidate.family == "t"]
    assert drift and drift[0].drift_source.preferred == "leg zeros", [f.words for f in drift]
    doc = diag.as_json()["discovered"][diag.discovered.index(drift[0])]["drift_source"]
    assert doc["preferred"] == "leg zeros" and diag.instrument_drift is None
    assert "would move the table off" not in drift[0].words
    table, d = _drifting(True)
    diag = jt.diagnose(table, d, library=[], flexible=False, log=lambda _: None)
    assert not [f for f in diag.discovered if f.candidate.family == "t"], diag.discovered
    found = diag.instrument_drift
    assert found is not None and found.source.preferred == "instrument frame"
    assert "would move the table off" in found.words() and found.heldout_gain > 0.2
    assert diag.final.frame_drift is not None and not diag.unexplained
    doc = diag.as_json()["instrument_drift"]
    theta = np.deg2rad(20 / 3600)
    truth = {"x": theta * 200.0, "y": theta * 300.0, "z": 0.0, "roll": 0.0, "pitch": 0.0}
    truth["yaw"] = theta
    for dof, value in truth.items():
        key = f"frame_drift[1].{dof}"
        assert abs(doc["drift"][key] - value) < 3.5 * doc["std"][key], (dof, doc["drift"][key])
    assert "instrument drift" in diag.steps[-1].model
    # the model file does not carry it: no drift term, the frames as fitted at the start
    assert diag.fitted_model().effects.get("discovered") is None
