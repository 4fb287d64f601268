"""The instrument frame drifting over time (a tracker or its stand warming up): a nuisance
fitted beside the frame (`calibrate(..., frame_drift=True)`, `--frame-drift`), and what
`diagnose` fits in place of a drift of the legs where the data prefer the instrument's."""

import dataclasses
import json

import numpy as np
import pytest

import jaxtable as jt
from jaxtable._calibration.simulate import concat
from jaxtable.cli import main

ARCSEC = np.deg2rad(1 / 3600)
UNITS = np.array([1e-3] * 3 + [ARCSEC] * 3)  # µm and arcsec in mm and rad


def _drifting_sessions(table, seed=0, n=80):
    """Two sessions of `n` stops, each with its tracker set up anew and drifting its own way
    (`simulate`'s clock runs over each session's rows: `drifts` (2, 6) is each session's
    change, first row to last); returns (data, drifts)."""
    true = jt.perturb_table(table, 900 + seed)
    drifts = np.array([[30, -20, 10, 3, -2, 4], [-15, 25, 5, -2, 4, 1]]) * UNITS
    frames = [(400, -100, 50, 0.01, -0.02, 0.3), (-300, 200, 40, -0.02, 0.01, -1.2)]
    runs = [
        jt.simulate(
            table,
            true,
            jt.plan_random(n, 950 + seed + k),
            jt.tracker6(),
            seed=seed + k,
            frame=frames[k],
            frame_drift=drifts[k],
            session=f"day {k + 1}",
        )  # fmt: skip
        for k in range(2)
    ]
    d = concat(*runs)
    return dataclasses.replace(d, sigma=None), drifts


def test_frame_drift_columns_are_the_frame_s_times_the_time(table):
    """The residual reads the frame at a row as frame + drift · t (t the file's time), so
    the fit's Jacobian column of each session's drift DOF is the frame DOF's column times
    each row's t, and zero on the other session's rows (the chain rule; the frame columns
    are checked against central differences in `test_calibration.py`)."""
    from jaxtable._calibration.fit import _flat, jacobian_in_chunks, setup

    d, _ = _drifting_sessions(table, n=20)
    st = setup(table, d, jt.GEOMETRY, frame_drift=True)
    theta = dict(st.theta0)
    theta["frame_drift"] = 1e-3 * np.arange(12.0).reshape(2, 6)  # a point off zero
    J, _, solved = jacobian_in_chunks(st.problem, st.layout, theta)
    assert np.all(solved)
    t = np.repeat(np.asarray(st.problem.ctx.time), 6)
    session = np.repeat(np.asarray(st.problem.session), 6)
    assert np.ptp(t) > 0.9
    for s in range(2):
        for dof in ("x", "y", "z", "roll", "pitch", "yaw"):
            f = J[:, st.names.index(f"frame[{s + 1}].{dof}")]
            g = J[:, st.names.index(f"frame_drift[{s + 1}].{dof}")]
            assert np.any(f != 0)
            np.testing.assert_allclose(g, f * t, rtol=1e-12, atol=1e-12 * np.abs(f).max())
            assert np.all(g[session != s] == 0)
    assert len(_flat(theta)) == len(st.names)


def test_a_drifting_tracker_is_fitted_as_a_nuisance(table, tmp_path, capsys):
    """Two sessions, a 6-D tracker set up anew in each and drifting 10–30 µm and 1–4″ over
    it, 5 µm / 2″ noise, no σ. Without the drift the fit takes it for noise (σ estimated
    > 1.3 × the truth, structure in time); with it the σ is the truth's to 10 % and each of
    the 12 drift components lies within 3.5 σ of the truth (the truth over the session:
    half the file's rate). The command line's `--frame-drift` writes the same lines, and
    refuses the drift without a frame."""
    from jaxtable._calibration.fit import fit_screened
    from jaxtable._discovery.structure import structure_test

    d, drifts = _drifting_sessions(table)
    st_still, still = fit_screened(table, d, jt.GEOMETRY)
    assert still.frame_drift is None
    assert still.group_sigma()["positions"] > 1.3 * 0.005, still.group_sigma()
    assert structure_test(still, st_still).structure
    st, cal = fit_screened(table, d, jt.GEOMETRY, frame_drift=True)
    sig = cal.group_sigma()
    assert sig["positions"] == pytest.approx(0.005, rel=0.1), sig
    assert sig["angles"] == pytest.approx(2 * ARCSEC, rel=0.1), sig
    assert not structure_test(cal, st).structure
    np.testing.assert_allclose(cal.session_span, [79 / 159, 79 / 159], rtol=1e-12)
    for s in range(2):
        for k, dof in enumerate(("x", "y", "z", "roll", "pitch", "yaw")):
            i = cal.names.index(f"frame_drift[{s + 1}].{dof}")
            # the fit's drift is per file time; the simulated one over each run, first row
            # to last
            z = (cal.value[i] * cal.session_span[s] - drifts[s, k]) / (
                cal.std[i] * cal.session_span[s]
            )
            assert abs(z) < 3.5, (s, dof, z)
    lines = cal.frame_drift_lines()
    assert len(lines) == 2 and lines[0].startswith("instrument frame drift over session 1")
    assert lines[0] in cal.report()
    # the model file keeps each session's frame where the instrument was at its last row:
    # the last 10 stops of each session, predicted through the stored frames, agree with
    # the model to about their noise (the drift within them: up to 30 µm / 8); through the
    # frames at the file's time 0 they do not
    model = jt.fitted_model(cal, table, d.sessions)
    ends = cal.frame + cal.frame_drift * cal.session_time[:, 1:]
    for k, label in enumerate(d.sessions):
        np.testing.assert_allclose(model.instrument.frames[label], ends[k], rtol=0, atol=1e-12)
    tail = d.subset(np.r_[70:80, 150:160])
    v = jt.validate(model, tail)
    assert all(f["source"] == "stored" for f in v.frames.values())
    assert max(v.rms[c] for c in ("x", "y", "z")) < 1.6 * 0.005, v.rms
    start = {lab: np.asarray(cal.frame[k]) for k, lab in enumerate(d.sessions)}
    stale = dataclasses.replace(model.instrument, frames=start)
    v = jt.validate(dataclasses.replace(model, instrument=stale), tail)
    assert max(v.rms[c] for c in ("x", "y", "z")) > 3 * 0.005, v.rms
    path = tmp_path / "drift.csv"
    jt.save_measurements(d, path)
    assert main(["calibrate", str(path), "--frame-drift", "--out", str(tmp_path / "c")]) == 0
    printed = capsys.readouterr().out
    assert "instrument frame drift over session 2, first row to last" in printed
    assert main(["calibrate", str(path), "--frame-drift", "--no-frame"]) == 2
    assert "--frame-drift: the instrument frame is not estimated" in capsys.readouterr().err
    with pytest.raises(ValueError, match="frame_drift: the instrument frame is not estimated"):
        jt.calibrate(table, d, jt.GEOMETRY, frame_drift=True, estimate_frame=False)


# --- validate on a new day whose tracker drifts ----------------------------------------------

FRAME_A = (50.0, -30.0, 20.0, np.deg2rad(1.2), np.deg2rad(-0.9), np.deg2rad(2.0))
FRAME_B = (-20.0, 40.0, 5.0, np.deg2rad(-0.5), np.deg2rad(0.7), np.deg2rad(-1.5))
TARGET = (30.0, -20.0, 80.0, 0.0, 0.0, 0.0)
DAY2_DRIFT = np.array([30, -20, 10, 3, -2, 4]) * UNITS  # over the day, first row to last
POSE = ("x", "y", "z", "roll", "pitch", "yaw")


def _model(table, k):
    """(true table, a model fitted on 80 stops of a still tracker, session A)."""
    true = jt.perturb_table(table, 100 + k)
    a = jt.simulate(table, true, jt.plan_random(80, 200 + k), jt.tracker6(), frame=FRAME_A,
                    target=TARGET, session="A", seed=300 + k)  # fmt: skip
    return true, jt.fitted_model(jt.calibrate(table, a), table, a.sessions)


def _day2(table, true, k, drift=DAY2_DRIFT, frame=FRAME_B, label="B"):
    """60 new stops measured by a tracker set up anew (`frame`, session `label`) drifting by
    `drift` (6,) over them."""
    return jt.simulate(table, true, jt.plan_random(60, 400 + k), jt.tracker6(), frame=frame,
                       target=TARGET, session=label, seed=500 + k, frame_drift=drift)  # fmt: skip


def _drift_z(v, drift=DAY2_DRIFT) -> np.ndarray:
    """(6,) (registered − true change over the session) / its σ."""
    d = v.frames["B"]["drift"]
    file_units = np.array([1.0] * 3 + [np.rad2deg(1.0)] * 3)
    got = np.array([d["change"][c] for c in POSE])
    std = np.array([d["std"][c] for c in POSE])
    return (got - drift * file_units) / std


def test_validate_registers_a_new_day_s_drifting_tracker(table, tmp_path, capsys):
    """A model fitted with a still tracker predicts 60 stops of a new day whose tracker,
    set up anew, drifts 10–30 µm and 2–4″ over them. Its frame registered still on the
    first 10 stops, the prediction errs by more than the noise on the positions (a model
    that holds, taken for a failing one) and validate says the residuals drift in time;
    with `frame_drift` the frame and its drift are registered on 10 stops spread over the
    day (its first and last among them), both groups are within the noise, and each
    registered change lies within 3.5 σ of the truth. The command line's --frame-drift
    prints and reports the same, and refuses one registration stop."""
    true, model = _model(table, 0)
    day2 = _day2(table, true, 0)
    still = jt.validate(model, day2, register=10)
    ratio, _, bound = still.noise_groups["positions"]
    assert ratio > bound, still.noise_groups
    assert set(still.time_trend) == {"B"}, still.time_trend
    p, column, change = still.time_trend["B"]
    assert p < 1e-6 and column in POSE[:3], still.time_trend
    assert still.trend_lines()[0].startswith("session B: the predicted residuals drift in time")
    assert still.frames["B"]["drift"] is None
    v = jt.validate(model, day2, register=10, frame_drift=True)
    for g, (r, e, b) in v.noise_groups.items():
        assert r < b, (g, r, e, b)
    assert v.time_trend == {}
    # within the noise through a registered frame: said with what registration hides; not
    # through the stored frame
    assert "takes up much of a change of the legs since the fit" in v.noise_words()
    stored = jt.validate(model, _day2(table, true, 0, drift=np.zeros(6), frame=FRAME_A,
                                      label="A"))  # fmt: skip
    assert "within the noise the model's fit found" in stored.noise_words()
    assert "takes up much" not in stored.noise_words()
    # the registration: 10 stops spread over the day, its first and last among them
    rows = np.flatnonzero(v.registered)
    assert len(rows) == 10 and rows[0] == 0 and rows[-1] == len(day2) - 1, rows
    assert np.all(np.diff(rows) >= 5), rows
    z = _drift_z(v)
    assert np.all(np.abs(z) < 3.5), z
    # the pose reported is the frame at the day's first row: where the model's geometry
    # puts the still tracker of the same day without its drift, registered on every stop
    still_day = _day2(table, true, 0, drift=np.zeros(6))
    with pytest.warns(UserWarning, match="every row was used to register a frame"):
        ref = jt.validate(model, still_day).frames["B"]["pose"]
    np.testing.assert_allclose(v.frames["B"]["pose"], ref, rtol=0, atol=0.02)
    assert v.drift_lines()[0].startswith("session B: the instrument frame drifted over the")
    model_path = jt.save_fitted_model(model, tmp_path / "model.toml")
    jt.save_measurements(day2, tmp_path / "day2.csv")
    argv = ["validate", str(model_path), str(tmp_path / "day2.csv"), "--register", "10"]
    out = tmp_path / "v"
    assert main(argv + ["--frame-drift", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert v.drift_lines()[0] in printed, printed
    assert "within the noise the model's fit found" in printed
    assert v.drift_lines()[0] in (out / "report.md").read_text()
    doc = json.loads((out / "validation.json").read_text())
    for c, x in v.frames["B"]["drift"]["change"].items():  # the file's digits aside
        assert doc["frames"]["B"]["drift"]["change"][c] == pytest.approx(x, rel=1e-6)
    assert doc["time_trend"] == {}
    assert main(argv + ["--out", str(out)]) == 0
    assert "the predicted residuals drift in time" in capsys.readouterr().out
    doc = json.loads((out / "validation.json").read_text())
    assert doc["time_trend"]["B"]["p"] == pytest.approx(p, rel=1e-9)
    assert main(argv[:-1] + ["1", "--frame-drift", "--out", str(out)]) == 2
    assert "it needs at least 2 stops of each new session" in capsys.readouterr().err
    # stored frames are used as stored: --frame-drift on more rows of session A says so
    # (the tracker as the fit left it, drifting since)
    path_a = tmp_path / "a.csv"
    jt.save_measurements(_day2(table, true, 0, frame=FRAME_A, label="A"), path_a)
    assert main(["validate", str(model_path), str(path_a), "--frame-drift", "--out", str(out)]) == 0
    printed = capsys.readouterr()
    assert "no drift was registered" in printed.err
    # and its residuals drift in time: named, the frame stored
    assert "session A: the predicted residuals drift in time" in printed.out, printed.out
    assert "this session's frame is the model's, used as stored" in printed.out
    with pytest.warns(UserWarning, match="stored frames are used as stored"):
        jt.validate(model, jt.load_measurements(path_a), frame_drift=True)


@pytest.mark.slow
def test_a_drift_registered_on_a_new_day_over_200_tables(table):
    """200 tables, each fitted on 80 stops of a still tracker, then 60 stops of a new day
    predicted with the frame registered on 10 stops: (a) a tracker drifting 10–30 µm and
    2–4″ over the day, its drift registered with the frame (`frame_drift`): a model that
    holds goes above the noise bound (≥ 99.9 % for each group) in at most 2 of 200, the
    mean log(ratio / expected) is within ±0.03 (the leverage of a frame extrapolated in
    time is in the expected ratio), and the 1,200 registered changes' z = (registered −
    true) / σ have mean within ±0.1 and SD within 0.9–1.1; (b) a still tracker, registered
    still as a new session, or session A's as the fit left it (stored): the residuals are
    named as drifting in time (p < `TREND_P` = 0.001) in at most 2 of 200 each way (at a
    0.2 % rate 3 or more come in 1 %)."""
    from jaxtable._calibration.validate import TREND_P

    above, trend, logs, zs = 0, np.zeros(2, int), [], []
    for k in range(200):
        true, model = _model(table, k)
        v = jt.validate(model, _day2(table, true, k), register=10, frame_drift=True)
        above += any(r > b for r, _, b in v.noise_groups.values())
        logs.append([np.log(r / e) for r, e, _ in v.noise_groups.values()])
        zs.append(_drift_z(v))
        for way, (frame, label, register) in enumerate(((FRAME_B, "B", 10), (FRAME_A, "A", None))):
            still = _day2(table, true, k, drift=np.zeros(6), frame=frame, label=label)
            found = jt.validate(model, still, register=register).time_trend
            trend[way] += bool(found)
            assert all(p < TREND_P for p, _, _ in found.values())
    zs = np.ravel(zs)
    assert above <= 2, above
    np.testing.assert_array_less(np.abs(np.mean(logs, axis=0)), 0.03)
    assert abs(np.mean(zs)) < 0.1 and 0.9 < np.std(zs) < 1.1, (np.mean(zs), np.std(zs))
    assert np.all(trend <= 2), trend


def test_the_time_trend_p_value_has_its_law_on_noise():
    """`time_trend` on 2000 noise-only residual sets (50 rows, columns of different σ, a few
    lost cells, an uneven clock): its p (Bonferroni over the columns of the smallest
    per-column p) has the law P(p ≤ x) = 1 − (1 − x / 6)⁶ (Kolmogorov–Smirnov, on p < 1;
    the mass at p = 1 as that law gives it); a drift of 3 σ over the rows is found in
    every set at p < 1e-3."""
    from scipy.stats import kstest

    from jaxtable._calibration.validate import TREND_P, time_trend

    rng = np.random.default_rng(7)
    sigma = np.array([1.0, 1.0, 3.0, 0.1, 0.1, 0.2])
    ps, found = [], 0
    for _ in range(2000):
        t = np.sort(rng.uniform(0, 1, 50))
        e = rng.normal(0, 1, (50, 6)) * sigma
        e[rng.integers(0, 50, 5), rng.integers(0, 6, 5)] = np.nan
        ps.append(time_trend(e, t)[0])
        drifting = e + 3 * sigma * (t - 0.5)[:, None]
        found += time_trend(drifting, t)[0] < TREND_P
    ps = np.array(ps)
    law = lambda x: 1 - (1 - np.minimum(x, 6) / 6) ** 6  # noqa: E731
    inside = ps[ps < 1]
    # conditional law on p < 1: F(x) / F(1)
    assert kstest(inside, lambda x: law(x) / law(1.0)).pvalue > 0.01
    assert abs(np.mean(ps == 1) - (1 - law(1.0))) < 4 * np.sqrt(law(1.0) * (1 - law(1.0)) / 2000)
    assert found == 2000
