"""Calibration on simulated data with known truth: coverage, held-out accuracy, instrument
frames and sessions, unidentifiable directions, bad input."""

import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from jaxtable._calibration.fit import calibrate, validate
from jaxtable._calibration.instruments import interferometer, point_tracker, tracker6
from jaxtable._calibration.measurements import DataFileError, load_measurements, save_measurements
from jaxtable._calibration.simulate import concat, perturb_table, plan_random, plan_x_line, simulate

FRAME = (50.0, -30.0, 20.0, np.deg2rad(1.2), np.deg2rad(-0.9), np.deg2rad(2.0))  # 50 mm, ~2°


def truth_in_fit_coordinates(nominal, true, cal):
    """True values of the fitted joint/L0 parameters: joint errors projected on the non-rigid
    directions (the gauge), L0 errors as they are."""
    out = {}
    for name in ("base_joints", "platform_joints"):
        d = (np.asarray(getattr(true, name)) - np.asarray(getattr(nominal, name))).ravel()
        z = cal.bases[name].T @ d
        out.update({f"{name}.g{i + 1}": v for i, v in enumerate(z)})
    dl = np.asarray(true.zero_lengths) - np.asarray(nominal.zero_lengths)
    out.update({f"zero_lengths[{i + 1}]": v for i, v in enumerate(dl)})
    return out


def assert_within(cal, prefix, truth, k=4.0):
    """Fitted frame/target components within k σ of the truth (they trade off with the
    L0 and joint errors, so their own σ, not a fixed tolerance, is the yardstick)."""
    labels = "x y z roll pitch yaw".split()
    for j, name in enumerate(cal.names):
        if name.startswith(prefix):
            d = labels.index(name.rsplit(".", 1)[1])
            assert abs(cal.value[j] - truth[d]) < k * cal.std[j], (name, cal.value[j], truth[d])


def run_case(nominal, seed, frame=(0.0,) * 6, n_fit=120, n_held=200):
    true = perturb_table(nominal, seed)
    fit = simulate(nominal, true, plan_random(n_fit, seed), tracker6(), frame=frame, seed=seed)
    held = simulate(
        nominal,
        true,
        plan_random(n_held, 10_000 + seed),
        tracker6(),
        frame=frame,
        seed=20_000 + seed,
    )
    cal = calibrate(nominal, fit)
    truth = truth_in_fit_coordinates(nominal, true, cal)
    z = np.array(
        [(cal.value[k] - truth[n]) / cal.std[k] for k, n in enumerate(cal.names) if n in truth]
    )
    return cal, z, validate(cal, nominal, held)


NOISE = dict(zip("x y z roll pitch yaw".split(), tracker6().noise))


def test_known_truth_over_40_seeds(table):
    """Identifiable parameters (joints modulo rigid motions, L0) within 3σ of truth for
    >= 95 % of parameter-seed pairs; held-out RMS within 1.2x the instrument noise."""
    zs, worst = [], 0.0
    for seed in range(40):
        cal, z, held = run_case(table, seed)
        assert cal.converged and not cal.unidentifiable
        zs.append(z)
        worst = max(worst, max(held[c] / NOISE[c] for c in held))
    zs = np.concatenate(zs)
    assert np.mean(np.abs(zs) < 3) >= 0.95
    assert 0.8 < zs.std() < 1.25  # the covariance is honest, not just loose
    assert worst < 1.2


def test_shifted_frame_and_two_sessions_calibrate_as_well(table):
    seed = 3
    _, z0, held0 = run_case(table, seed)
    cal1, z1, held1 = run_case(table, seed, frame=FRAME)
    assert_within(cal1, "frame[1]", FRAME)  # the frame is recovered
    assert np.mean(np.abs(z1) < 3) >= 0.95
    for c in held0:
        assert held1[c] < 1.2 * NOISE[c]
    # two sessions: the tracker set up anew between them
    true = perturb_table(table, seed)
    frame2 = (-40.0, 60.0, -10.0, np.deg2rad(-1.5), np.deg2rad(0.7), np.deg2rad(-2.0))
    s1 = simulate(table, true, plan_random(40, 1), tracker6(), frame=FRAME, session="a", seed=1)
    s2 = simulate(table, true, plan_random(40, 2), tracker6(), frame=frame2, session="b", seed=2)
    cal = calibrate(table, concat(s1, s2))
    assert cal.converged and cal.frame.shape == (2, 6)
    assert_within(cal, "frame[1]", FRAME)
    assert_within(cal, "frame[2]", frame2)
    held = concat(
        simulate(table, true, plan_random(100, 5), tracker6(), frame=FRAME, session="a", seed=5),
        simulate(table, true, plan_random(100, 6), tracker6(), frame=frame2, session="b", seed=6),
    )
    for c, v in validate(cal, table, held).items():
        assert v < 1.2 * NOISE[c], c


def _check_redundancy(cal):
    """The fit's redundancy numbers (from its identifiability SVD) = `noise.redundancy` of
    its Jacobian, and they sum to the degrees of freedom (observations − rank)."""
    from jaxtable._calibration.noise import redundancy

    np.testing.assert_allclose(cal.redundancy, redundancy(cal.jacobian), rtol=0, atol=1e-12)
    assert cal.redundancy.sum() == pytest.approx(cal.dof, abs=1e-8)
    assert np.all(cal.redundancy[~np.any(cal.jacobian != 0, axis=1)] == 0)


def test_point_tracker_with_target_offset(table):
    true = perturb_table(table, 8)
    target = (30.0, -20.0, 80.0, 0.0, 0.0, 0.0)
    fit = simulate(table, true, plan_random(80, 8), point_tracker(), frame=FRAME, target=target)
    cal = calibrate(table, fit)
    assert cal.converged and not cal.unidentifiable
    _check_redundancy(cal)  # three of six columns measured: unused cells have r = 0
    assert_within(cal, "target", target)
    assert_within(cal, "frame[1]", FRAME)
    held = simulate(
        table, true, plan_random(200, 9), point_tracker(), frame=FRAME, target=target, seed=9
    )
    for c, v in validate(cal, table, held).items():
        assert v < 1.2 * point_tracker().noise[0], c


def test_x_interferometer_reports_unidentifiable_directions(table):
    """The paper's experiment: x only, on the x line. Most of the 42 parameters cannot be
    separated; the fit says so (std = inf) instead of returning confident numbers."""
    true = perturb_table(table, 4)
    data = simulate(table, true, plan_x_line(), interferometer())
    cal = calibrate(table, data)
    assert len(cal.unidentifiable) >= 20
    assert np.isinf(cal.std).sum() >= 20
    _check_redundancy(cal)  # rank-deficient: the hat matrix of the kept directions
    text = cal.report()
    assert "cannot determine" in text and "zero length L0" in text
    assert cal.rms_after["x"] < 2 * interferometer().noise[0]  # it still fits the data


def test_csv_round_trip_and_bad_files(table, tmp_path):
    true = perturb_table(table, 1)
    m = simulate(table, true, plan_random(10, 1), tracker6())
    m.extra["operator"] = np.array(["ab"] * 10)
    save_measurements(m, tmp_path / "m.csv")
    back = load_measurements(tmp_path / "m.csv")
    np.testing.assert_allclose(back.measured, m.measured, atol=1e-12)
    np.testing.assert_array_equal(back.cmd_lengths, m.cmd_lengths)
    assert back.extra["operator"].tolist() == ["ab"] * 10
    lines = (tmp_path / "m.csv").read_text().splitlines()
    header = lines[0].split(",")

    def write(name, rows):
        p = tmp_path / name
        p.write_text("\n".join(rows) + "\n")
        return p

    # non-numeric cell: row and column named
    bad = lines[3].split(",")
    bad[header.index("cmd_pitch")] = "abc"
    with pytest.raises(DataFileError, match=r"row 3, column 'cmd_pitch': 'abc' is not a number"):
        load_measurements(write("a.csv", [lines[0]] + lines[1:3] + [",".join(bad)]))
    # missing commanded value
    bad = lines[2].split(",")
    bad[header.index("cmd_x")] = ""
    with pytest.raises(DataFileError, match=r"row 2, column 'cmd_x': missing value"):
        load_measurements(write("b.csv", [lines[0], lines[1], ",".join(bad)]))
    # no measured column
    keep = [
        k
        for k, h in enumerate(header)
        if h not in "x y z roll pitch yaw".split() and not h.startswith("sigma_")
    ]
    rows = [",".join(line.split(",")[k] for k in keep) for line in lines]
    with pytest.raises(DataFileError, match="no measured column"):
        load_measurements(write("c.csv", rows))
    # a commanded pose outside the stroke: refused by row and leg
    bad = lines[4].split(",")
    bad[header.index("cmd_l3")] = "1200.0"
    data = load_measurements(write("d.csv", [lines[0]] + lines[1:5]))
    data_bad = load_measurements(write("e.csv", [lines[0]] + lines[1:4] + [",".join(bad)]))
    calibrate(table, data, free=("zero_lengths",), estimate_frame=False)
    with pytest.raises(ValueError, match=r"row 4: commanded length of leg 3 \(1200.000 mm\)"):
        calibrate(table, data_bad)


def test_fit_jacobian_equals_central_differences(table):
    """The fit's Jacobian (reverse mode row by row, through the forward solve's implicit
    derivative) = central differences of the weighted residual, in every kind of parameter:
    joints, zero lengths, the spiral lead, backlash and compliance (whose leg forces solve
    the statics at each pose; a 20 kg payload in session 2) and the frames of two tracker
    sessions, at a point where every parameter has moved from its start. Evaluated 3 stops
    at a time (`jacobian_in_chunks`: the 24 stops as 8 blocks of one compiled program, run
    from the pool of host threads (`POOL_BLOCKS`) and each embedded into J's rows as it
    comes; its rows are those of `jacobian` and of the fit's loop), with the residual of
    the whole set and every solve flag."""
    import jax.numpy as jnp
    from jax.flatten_util import ravel_pytree

    from jaxtable._calibration.fit import (
        POOL_BLOCKS,
        _scales,
        jacobian_in_chunks,
        residual_jit,
        setup,
    )
    from jaxtable._effects import Backlash, Compliance, Spiral
    from jaxtable._params import GEOMETRY

    true = perturb_table(table, seed=21)
    eff = {"spiral": Spiral(12.7 * np.ones(6)), "backlash": Backlash(0.01)}
    eff["compliance"] = Compliance(5e-5)
    runs = [
        simulate(
            table,
            true,
            plan_random(12, seed=22 + k),
            tracker6(),
            effects=eff,
            session=str(k + 1),
            payload=20.0 * k,
            frame=(0.5 * k, 0, 0, 0, 0, 0.001 * k),
            seed=k,
        )
        for k in range(2)
    ]
    model = {"spiral": Spiral.from_table(table), "backlash": Backlash()}
    model["compliance"] = Compliance()
    free = GEOMETRY + ("spiral.lead", "backlash.w", "compliance.flex")
    st = setup(table, concat(*runs), free, effects=model)
    flat, unravel = ravel_pytree(st.theta0)

    def jac(theta):
        return jacobian_in_chunks(st.problem, st.layout, theta, rows=3)

    assert 24 // 3 >= POOL_BLOCKS

    J0 = jac(st.theta0)[0]
    assert np.all(np.linalg.norm(J0, axis=0) > 0)  # every parameter matters
    # D: a step of D_j moves the weighted residual by about one unit
    D = np.asarray(_scales(J0.T @ J0, np.ones(flat.shape)))
    f = np.asarray(flat) + D * np.random.default_rng(0).standard_normal(flat.shape)
    J, r, solved = jac(unravel(jnp.asarray(f)))
    assert J.shape == (24 * 6, flat.size) and solved.shape == (24,) and np.all(solved)

    def res(x):
        return np.asarray(residual_jit(unravel(jnp.asarray(x)), (st.problem, st.layout)))

    h = 0.1 * D
    Jfd = np.stack(
        [
            (res(f + h[j] * e) - res(f - h[j] * e)) / (2 * h[j])
            for j, e in enumerate(np.eye(f.size))
        ],
        axis=1,
    )
    err = np.linalg.norm(J - Jfd, axis=0) / np.linalg.norm(Jfd, axis=0)
    assert err.max() < 1e-6, (err.max(), st.names[int(np.argmax(err))])
    assert {"spiral.lead[1]", "backlash.w[1]", "compliance.flex[1]"} <= set(st.names)
    np.testing.assert_allclose(r, res(f), rtol=1e-12, atol=1e-12)


def test_truncated_step_is_the_truncated_pseudo_inverse():
    """The Gauss-Newton step (from eigh of the Gram matrix) against −pinv(A, rcond) r from
    numpy's SVD, on unit-norm columns as the fit scales them. With an exactly dependent
    column (dropped) and the rest well conditioned: the same step. With also a weak but
    identifiable column (σ = 7e-5 of the largest, kept): a step that differs by rounding
    amplified by κ² (κ = σ_max / σ of the weakest kept direction: the price of the Gram
    matrix; an SVD would amplify by κ), so the same change of the residual, A·step, to
    1e-7 (of ~1). Full rank: least squares. A NaN entry: a step of NaN."""
    from jaxtable._calibration.fit import _truncated_step

    rng = np.random.default_rng(3)
    A = rng.standard_normal((200, 12))
    A[:, 5] = A[:, 2] - 0.5 * A[:, 7]  # no information: dropped
    r = rng.standard_normal(200)

    def unit(M):
        return M / np.linalg.norm(M, axis=0)

    def pinv_step(M):
        return -np.linalg.pinv(M, rcond=1e-6) @ r

    B = unit(A)
    np.testing.assert_allclose(np.asarray(_truncated_step(B, r, 1e-6)), pinv_step(B), atol=1e-12)
    A[:, 9] = A[:, 3] + 1e-4 * rng.standard_normal(200)  # weak but identifiable: kept
    B = unit(A)
    sv = np.linalg.svd(B, compute_uv=False)
    assert 1e-6 * sv[0] < sv[-2] < 1e-4 * sv[0] and sv[-1] < 1e-12 * sv[0]
    step, ref = np.asarray(_truncated_step(B, r, 1e-6)), pinv_step(B)
    kappa2 = (sv[0] / sv[-2]) ** 2
    assert np.linalg.norm(step - ref) < 10 * np.finfo(float).eps * kappa2 * np.linalg.norm(ref)
    np.testing.assert_allclose(B @ step, B @ ref, atol=1e-7)
    C = np.delete(B, 5, axis=1)
    np.testing.assert_allclose(
        np.asarray(_truncated_step(C, r, 1e-6)),
        -np.linalg.lstsq(C, r, rcond=None)[0],
        rtol=1e-6,
    )
    B[7, 2] = np.nan  # a residual or Jacobian that is not finite: no step (not an error)
    assert np.all(np.isnan(_truncated_step(B, r, 1e-6)))


def test_fits_of_any_number_of_stops_share_one_compiled_program(table):
    """Data sets of 23, 64 and 150 stops (part of a block, one block, three blocks with the
    last padded) fit and validate with one compiled program each for the fit and the
    residual of their model structure, not one per number of stops; the blocked Jacobian
    equals the one evaluated as a single block of all the stops, padded rows add nothing,
    and each fit recovers the planted zero-length errors within 4 σ."""
    from conftest import compiled_programs

    from jaxtable._calibration.fit import jacobian_in_chunks, setup

    true = perturb_table(table, 31)
    dl = np.asarray(true.zero_lengths) - np.asarray(table.zero_lengths)
    with compiled_programs() as compiles:
        for n in (23, 64, 150):
            data = simulate(table, true, plan_random(n, 31 + n), point_tracker(), seed=n)
            cal = calibrate(table, data, ("zero_lengths",))
            assert cal.converged
            value, std = cal.parameter("zero_lengths")
            z = (value - dl) / std
            assert np.all(np.abs(z) < 4), (n, z)
            assert set(validate(cal, table, data)) == {"x", "y", "z"}
    assert compiles.count("jit(_block_jacobian)") <= 1, compiles
    assert compiles.count("jit(residual)") <= 1, compiles
    st = setup(table, data, ("zero_lengths",))
    one = jacobian_in_chunks(st.problem, st.layout, cal.theta, rows=150)
    blocked = jacobian_in_chunks(st.problem, st.layout, cal.theta)
    for a, b in zip(one, blocked):
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12)
    J, r, _ = blocked
    assert J.shape == (900, len(st.names))
    np.testing.assert_allclose(r.reshape(-1, 6)[:, 3:], 0.0)  # angles not measured


def test_fits_of_other_parameters_and_instruments_share_one_compiled_jacobian(table):
    """One model structure (the spiral term) compiles the fit's block Jacobian once,
    whatever the fit frees and the instrument reads: the geometry seen by a 6-D tracker
    (joint sets gauged, every frame and target DOF), by a point tracker (the target's
    position only) and by an x interferometer (three frame DOFs, no gauge), the geometry
    with the lead per leg and as one number for all legs, a file of two sessions (a frame
    each), the zero lengths alone; and a fit runs on it. The Jacobians of the layouts agree
    as the parameters are related: a gauged joint set's columns are the plain coordinates'
    columns times its basis, the shared lead's column the sum of the six per-leg leads'."""
    from conftest import compiled_programs

    from jaxtable._calibration.fit import jacobian_in_chunks, setup
    from jaxtable._params import GEOMETRY

    true = perturb_table(table, 5)
    poses = plan_random(30, 5)
    readers = {"tracker": tracker6(), "point": point_tracker(), "x": interferometer()}
    data = {k: simulate(table, true, poses, inst, seed=1) for k, inst in readers.items()}
    later = simulate(table, true, poses[:20], tracker6(), session="B", frame=FRAME, seed=2)
    two = concat(data["tracker"], later)
    per_leg = GEOMETRY + ("spiral.lead",)
    with compiled_programs() as compiles:
        st = {
            "gauged": setup(table, data["tracker"], per_leg),
            "plain": setup(table, data["tracker"], per_leg, estimate_frame=False),
            "shared": setup(table, data["tracker"], GEOMETRY + ("spiral.lead[all]",)),
            "point": setup(table, data["point"], GEOMETRY),
            "x": setup(table, data["x"], GEOMETRY),
            "two": setup(table, two, per_leg),
        }
        assert st["two"].layout.n_sessions == 2
        assert st["gauged"].layout.gauge == ("base_joints", "platform_joints")
        assert st["point"].layout.target_dofs == (0, 1, 2)
        assert st["x"].layout.frame_dofs == (0, 4, 5) and not st["x"].layout.gauge
        J = {}
        for k, s in st.items():
            theta = dict(s.theta0)  # every layout at the same model: frame and target at 0
            theta.update({n: 0 * theta[n] for n in ("frame", "target") if n in theta})
            J[k] = jacobian_in_chunks(s.problem, s.layout, theta)[0]
            rows = 6 * len(s.mask)
            assert J[k].shape == (rows, len(s.names)) and np.all(np.isfinite(J[k])), k
        cal = calibrate(table, data["x"], ("zero_lengths",))
        assert cal.converged
    assert compiles.count("jit(_block_jacobian)") <= 1, compiles

    def columns(k, prefix):
        return J[k][:, [i for i, n in enumerate(st[k].names) if n.startswith(prefix)]]

    for joints in ("base_joints", "platform_joints"):
        basis = np.asarray(st["gauged"].problem.bases[joints])  # (18, 12)
        np.testing.assert_allclose(
            columns("gauged", joints), columns("plain", joints) @ basis, rtol=0, atol=1e-12
        )
    np.testing.assert_allclose(
        columns("shared", "spiral.lead[all]")[:, 0],
        columns("gauged", "spiral.lead").sum(axis=1),
        rtol=0,
        atol=1e-12,
    )


def test_damped_step_solves_the_trust_region_problem():
    """The trust region's step (`_TruncatedGram.within`) against its optimality conditions
    (Moré & Sorensen): (G + μI) p = −g with μ ≥ 0 and |p| = Δ (to the 1 % the fit asks)
    when the Gauss-Newton step is longer than Δ, else μ = 0 and the Gauss-Newton step.
    The predicted decrease against |r|² − |r + A p|² computed directly. On unit-norm
    columns with a dependent column (its direction dropped, g has no component there) and a
    weak one (σ = 7e-5 of the largest), as the fit scales them."""
    from jaxtable._calibration.fit import _truncated_step, _TruncatedGram

    rng = np.random.default_rng(3)
    A = rng.standard_normal((200, 12))
    A[:, 5] = A[:, 2] - 0.5 * A[:, 7]
    A[:, 9] = A[:, 3] + 1e-4 * rng.standard_normal(200)
    A /= np.linalg.norm(A, axis=0)
    r = rng.standard_normal(200)
    G, g = A.T @ A, A.T @ r
    model = _TruncatedGram(G, g, 1e-6)
    full = np.asarray(_truncated_step(A, r, 1e-6))
    null = np.linalg.svd(A)[2][-1]  # the dependent columns' direction
    lam = np.linalg.eigvalsh(G)
    rounding = np.finfo(float).eps * lam[-1] / lam[1]
    assert np.linalg.norm(A @ null) < 1e-12
    p, mu = model.within(1.5 * np.linalg.norm(full))
    assert mu == 0.0 and np.array_equal(p, full)
    for frac in (0.9, 0.3, 1e-3):
        radius = frac * np.linalg.norm(full)
        p, mu = model.within(radius)
        assert mu > 0 and abs(np.linalg.norm(p) / radius - 1) < 0.01, (frac, mu)
        # off the dropped direction n (where a plain solve divides rounding by μ)
        off = np.eye(12) - np.outer(null, null)
        expected = off @ -np.linalg.solve(G + mu * np.eye(12), g)
        np.testing.assert_allclose(off @ p, expected, rtol=1e-6, atol=1e-9)
        # what rounding leaves of the dropped direction: the weak direction's eigenvector is
        # known to about ε λ_max / λ_weak (its gap to the dropped one, 9e-8 here); a
        # LAPACK build or a permuted G gives up to ~0.7 of that, so within 10×
        assert abs(null @ p) < 10 * rounding * np.linalg.norm(p)
        # the decrease to the rounding of λ_weak (about ε λ_max) times the step's square (up
        # to 3e-8 of the decrease here): 0.01-0.06 of it with this LAPACK, up to 4.4 with G
        # permuted
        direct = r @ r - (r + A @ p) @ (r + A @ p)
        assert abs(model.reduction(p) - direct) < 20 * np.finfo(float).eps * lam[-1] * (p @ p)
        # a longer step predicts more decrease, a shorter one less: |p| sits on the boundary
        assert model.reduction(model.within(0.5 * radius)[0]) < model.reduction(p)


def test_gauss_newton_damps_the_steps_where_the_linearisation_fails(table):
    """8 stops of a 6-D tracker with every geometric parameter free (54 parameters on 48
    readings and the frame, directions near the truncation level): the undamped
    Gauss-Newton ran its 200 steps without converging (χ² above 1000 there) before LM took
    over. With the trust region Gauss-Newton itself converges, to LM's optimum (the
    independent reference: optimistix's Levenberg-Marquardt on the same problem)."""
    from jaxtable._calibration.fit import _solve, setup

    true = perturb_table(table, 2)
    data = simulate(table, true, plan_random(8, 4), tracker6(), seed=2)
    st = setup(table, data, compensated=True)
    mask = np.ones(ravel_pytree(st.theta0)[0].shape[0])
    args = (st.problem, st.layout, st.theta0, mask, 1e-8, 1e-8, 200)
    _, converged, steps, _, solved, _, r = _solve(*args, "gauss_newton")
    _, lm_converged, _, _, _, _, r_lm = _solve(*args, "levenberg_marquardt")
    assert converged and steps < 60 and np.all(solved), steps
    assert lm_converged
    assert r @ r == pytest.approx(r_lm @ r_lm, rel=1e-6)


def test_gauss_newton_follows_a_curved_valley(table):
    """The paper's x line read by the interferometer (17 stops, x only; 42 geometric
    parameters and the frame, of which a few combinations are determined): straight steps
    alternated between taken and shortened along a curved valley and ran out of steps (LM
    did not converge either). With geodesic acceleration the fit converges, at a point
    where numpy's truncated least squares (SVD, the fit's truncation level) finds no
    decrease of χ² beyond 1e-4 (residuals in σ: the rest of the way would move the
    estimate by ~1 % of its standard error; the straight steps stopped 0.01 short)."""
    from jaxtable._calibration.fit import _scales, _solve, setup

    true = perturb_table(table, 2)
    data = simulate(table, true, plan_x_line(), interferometer(), seed=2)
    st = setup(table, data, compensated=True)
    mask = np.ones(ravel_pytree(st.theta0)[0].shape[0])
    args = (st.problem, st.layout, st.theta0, mask, 1e-8, 1e-8, 200)
    _, converged, steps, J, solved, _, r = _solve(*args, "gauss_newton")
    assert converged and steps < 60 and np.all(solved), steps
    A = J * _scales(J.T @ J, mask)  # unit columns, as the fit scales them
    step = -np.linalg.pinv(A, rcond=1e-6) @ r
    decrease = r @ r - (r + A @ step) @ (r + A @ step)
    assert decrease <= 1e-4, (decrease, r @ r)
