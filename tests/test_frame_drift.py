"""The instrument frame drifting over time (a tracker or its stand warming up): a nuisance
fitted beside the frame (`calibrate(..., frame_drift=True)`, `--frame-drift`), and what
`diagnose` fits in place of a drift of the legs where the data prefer the instrument's."""

import dataclasses

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
