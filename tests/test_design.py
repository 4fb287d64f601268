"""Design studies: criteria against hand-derived cases (the cubic hexapod's stiffness, a mass
on springs, statics of a symmetric table), gradients against finite differences, smoothed worst
cases against their bounds, the optimiser against a brute-force grid and exhaustive
enumeration, bad input refused with the variable named, and the CLI verbs' contracts."""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import compiled_programs, quick_jit

import jaxtable as jt
from jaxtable._design.criteria import _soft_max, _soft_min, leg_matrix, pose_criteria
from jaxtable._design.variables import set_values, stack
from jaxtable._effects import GRAVITY

REF = jt.reference_table()


@pytest.fixture(scope="module")
def design():
    return jt.Design(jt.SymmetricDesign.from_table(REF), jt.hardware_for(REF))


@pytest.fixture(scope="module")
def few_poses():
    return jt.design_poses(None, n_sweep=3, n_random=8, box=2)


# ---------------------------------------------------------------- independent truths


def _cube_table(a: float, offset=(0.0, 0.0, 0.0)):
    """Legs along six edges of a cube of edge a (the zig-zag that avoids the two ends of the
    vertical body diagonal), the cube centre at `offset` from the platform origin (base
    axes, home). Returns (table, R) with R the rotation taking cube axes to base axes."""
    d = np.array([1.0, 1.0, 1.0]) / np.sqrt(3.0)
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(d, z)
    s, c = np.linalg.norm(v), d @ z
    V = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    R = np.eye(3) + V + V @ V * (1 - c) / s**2  # Rodrigues: R d = z
    lower, upper = [], []
    for i in range(3):  # vertices with one + coordinate -> neighbours with two
        lo = -np.ones(3) * a / 2
        lo[i] = a / 2
        for j in range(3):
            if j != i:
                up = lo.copy()
                up[j] = a / 2
                lower.append(R @ lo)
                upper.append(R @ up)
    h = 2 * a
    d = np.asarray(offset, dtype=float)  # cube centre relative to the platform origin
    base = np.array(lower) + d + np.array([0, 0, h])
    plat = np.array(upper) + d
    legs = np.array(upper) - np.array(lower)
    axes = np.cross(legs, [0.3, 0.5, 0.8])
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    table = jt.Table(base, plat, axes, axes, h, stroke=(0.0, 10 * a))
    return table, R


def test_cubic_configuration_stiffness_is_diagonal_at_the_cube_centre():
    a, k = 300.0, 1.5e4
    table, _ = _cube_table(a)
    K = np.asarray(jt.stiffness_matrix(table, jnp.zeros(6), k))
    expected = k * np.diag([2, 2, 2, a**2 / 2, a**2 / 2, 2 * a**2])
    np.testing.assert_allclose(K, expected, rtol=1e-12, atol=1e-9 * k * a**2)


def test_stiffness_off_the_cube_centre_has_the_coupling_of_a_moved_reference_point():
    # Cube centre C = O + d: v_C = v_O + ω × d = v_O − [d]× ω, so K_O = Tᵀ K_C T with
    # T = [[I, −[d]×], [0, I]].
    a, k = 300.0, 1.5e4
    d = np.array([40.0, -25.0, 60.0])
    table, _ = _cube_table(a, offset=d)
    K_C = k * np.diag([2, 2, 2, a**2 / 2, a**2 / 2, 2 * a**2])
    D = np.array([[0, -d[2], d[1]], [d[2], 0, -d[0]], [-d[1], d[0], 0]])
    T = np.block([[np.eye(3), -D], [np.zeros((3, 3)), np.eye(3)]])
    K = np.asarray(jt.stiffness_matrix(table, jnp.zeros(6), k))
    np.testing.assert_allclose(K, T.T @ K_C @ T, rtol=1e-10, atol=1e-8 * k * a**2)
    assert np.abs(K[:3, 3:]).max() > 50 * k  # the coupling is really there (2k|d|)


def test_first_frequency_of_the_cube_is_the_translational_spring_mass_one():
    # Translation block 2k I; with a small rotational inertia the lowest mode is a pure
    # translation: ω² = 2k·1000/m (k N/mm -> N/m).
    a, k, m = 300.0, 1.5e4, 80.0
    table, _ = _cube_table(a)
    hw = jt.Hardware(k, m, 1e3, 0.0, 0.0, 0.0, 0.9, 100.0)
    f = float(jt.first_frequency(table, hw))
    assert f == pytest.approx(math.sqrt(2 * k * 1e3 / m) / (2 * math.pi), rel=1e-10)


def test_leg_force_and_motor_duty_by_hand_at_home(design):
    # At home the symmetric table shares the weight equally: F = m g / (6 u_z) per leg
    # (compression); with a = 0 and ω = 0: rpm = 60 v / lead; torque = F lead / (2π η).
    table = design.table()
    hw = jt.hardware_for(table, acceleration=0.0, angular_velocity_deg=0.0, velocity=150.0)
    q = quick_jit(lambda p: pose_criteria(table, hw, p))(jnp.zeros(6))
    u = np.asarray(jt.leg_lengths(table, jnp.zeros(6)))
    uz = float(table.home_height) / u[0]
    m = float(hw.moving_mass(table))
    F = m * GRAVITY / (6 * uz)
    assert float(q["leg_force"]) == pytest.approx(F, rel=1e-10)
    assert float(q["motor_rpm"]) == pytest.approx(60 * 150.0 / 12.7, rel=1e-12)
    torque = F * 12.7 / (2 * math.pi * 0.9) / 1000
    assert float(q["motor_torque"]) == pytest.approx(torque, rel=1e-10)


def test_acceleration_adds_the_worst_direction_force(design):
    # The worst direction of an acceleration a gives |F0_i| + m a ‖row i of J⁻ᵀ G‖: check it
    # against a search over many directions.
    table = design.table()
    hw0 = jt.hardware_for(table, acceleration=0.0)
    hw = jt.hardware_for(table, acceleration=7.0)
    pose = jnp.array([30.0, -20.0, 10.0, 0.05, -0.03, 0.1])
    q = quick_jit(lambda p: pose_criteria(table, hw, p))(pose)
    J = np.asarray(quick_jit(lambda p: leg_matrix(table, p))(pose))
    f0 = np.asarray(quick_jit(lambda p: jt.leg_forces(table, p, hw0.payload))(pose))
    m = float(hw.moving_mass(table))
    dirs = np.random.default_rng(0).normal(size=(200000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    wrench = np.concatenate([-m * 7.0 * dirs, np.zeros_like(dirs)], axis=1)  # CoG at origin
    F = f0[None] + np.linalg.solve(J.T, wrench.T).T
    assert float(q["leg_force"]) == pytest.approx(np.abs(F).max(), rel=1e-4)
    assert float(q["leg_force"]) >= np.abs(F).max()


def test_lci_is_one_over_the_frobenius_condition_number_of_the_scaled_jacobian(design):
    table = design.table()
    hw = design.hardware
    pose = jnp.array([50.0, 20.0, -30.0, 0.1, 0.05, -0.2])
    J = np.asarray(quick_jit(lambda p: leg_matrix(table, p))(pose))
    ell = float(hw.characteristic_length)
    Jh = J * np.r_[np.ones(3), np.full(3, 1 / ell)]
    sv = np.linalg.svd(Jh, compute_uv=False)
    kappa_f = np.sqrt(np.sum(sv**2) * np.sum(sv**-2)) / 6  # ‖J‖_F ‖J⁻¹‖_F / n by SVD
    lci = float(quick_jit(lambda p: pose_criteria(table, hw, p))(pose)["lci"])
    assert lci == pytest.approx(1 / kappa_f, rel=1e-10)
    assert sv[-1] / sv[0] <= lci <= 6 * sv[-1] / sv[0]  # between 1/κ₂ and n/κ₂
    # the cube at its centre, ℓ = a/2: JᵀJ = diag(2, 2, 2, a²/2, a²/2, 2a²) scaled by 1/ℓ² in
    # rotation -> squared singular values 2, 2, 2, 2, 2, 8: LCI = 6 / sqrt(18 · 2.625)
    a = 300.0
    cube, _ = _cube_table(a)
    hw_cube = jt.Hardware(1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.9, a / 2)
    expected = 6 / math.sqrt((2 * 5 + 8) * (5 / 2 + 1 / 8))
    at_centre = quick_jit(lambda p: pose_criteria(cube, hw_cube, p))(jnp.zeros(6))
    assert float(at_centre["lci"]) == pytest.approx(expected)


# ---------------------------------------------------------------- gradients and smoothing


def test_gradients_of_every_criterion_equal_central_differences(design):
    poses = jt.design_poses(
        jt.Workspace(single=(400, 400, 300, 25, 25, 30), combined=(250, 250, 150, 15, 15, 20)),
        n_sweep=5,
        n_random=16,
        box=2,
    )
    names = ["base_radius", "platform_half_angle", "home_height", "lead", "leg_stiffness"]
    x0 = jnp.array([700.0, 0.17, 662.0, 12.7, 2.0e4])

    def crit(x):
        d = set_values(design, dict(zip(names, x)))
        c = jt.design_criteria(d.table(), d.hardware, jnp.asarray(poses), smooth=16.0)
        return jnp.stack([c[k] for k in jt.DESIGN_CRITERIA])

    def crit_twice(x):
        c = crit(x)
        return c, c

    # one program (criteria and their forward-mode Jacobian) for the values the central
    # differences take as well: compiling the criteria alone again took as long
    both = quick_jit(jax.jacfwd(crit_twice, has_aux=True))

    def f(x):
        return np.asarray(both(x)[1])

    G, c0 = (np.asarray(a) for a in both(x0))
    assert 0.05 < c0[0] < 0.999  # part of this workspace is out of reach: coverage has a slope
    h = np.array([1e-3, 1e-6, 1e-3, 1e-5, 1e-1])
    for j in range(len(names)):
        e = np.zeros(len(names))
        e[j] = h[j]
        fd = (f(x0 + e) - f(x0 - e)) / (2 * h[j])
        for i, k in enumerate(jt.DESIGN_CRITERIA):
            # atol: a change of 1e-6 of the criterion over the variable's own scale
            atol = 1e-6 * abs(c0[i]) / abs(float(x0[j])) + 1e-300
            np.testing.assert_allclose(
                G[i, j], fd[i], rtol=1e-4, atol=atol, err_msg=f"{k}/{names[j]}"
            )


def test_smoothed_worst_cases_bracket_and_converge_to_the_exact_ones(design, few_poses):
    table, hw = design.table(), design.hardware
    exact = jt.design_criteria(table, hw, jnp.asarray(few_poses))
    n = len(few_poses)
    for p in (4.0, 64.0, 1024.0):
        smooth = jt.design_criteria(table, hw, jnp.asarray(few_poses), smooth=p)
        for k, c in jt.DESIGN_CRITERIA.items():
            if k in ("coverage", "gci", "first_frequency_Hz"):
                continue
            e, s = float(exact[k]), float(smooth[k])
            # p-norms, on the safe side: max ≤ smooth ≤ max·n^(1/p), min·n^(−1/p) ≤ smooth ≤ min
            if c.sense == "min":
                assert e * (1 - 1e-12) <= s <= e * n ** (1 / p) * (1 + 1e-12), k
            else:
                assert e * n ** (-1 / p) * (1 - 1e-12) <= s <= e * (1 + 1e-12), k
    x = jnp.array([0.5, 1.0, 3.0, 2.0])
    assert float(_soft_max(x, 1e4)) == pytest.approx(3.0, rel=2e-4)
    assert float(_soft_min(x, 1e4)) == pytest.approx(0.5, rel=2e-4)
    # coverage: the sigmoid width τ → 0 gives the exact fraction
    ws = jt.Workspace(single=(400, 400, 300, 25, 25, 30), combined=(250, 250, 150, 15, 15, 20))
    big = jnp.asarray(jt.design_poses(ws, n_sweep=5, n_random=16, box=2))
    cov = float(jt.design_criteria(table, hw, big)["coverage"])
    smooth_cov = [
        float(jt.design_criteria(table, hw, big, smooth=8.0, coverage_width=w)["coverage"])
        for w in (10.0, 1e-3)
    ]
    assert 0 < cov < 1
    assert abs(smooth_cov[1] - cov) < 1e-6 < abs(smooth_cov[0] - cov)


# ---------------------------------------------------------------- optimisation


def test_another_tolerance_budget_runs_the_compiled_programs(design, few_poses):
    """A hardware's tolerances are float64 leaves like its other fields, not numbers built
    into the compiled programs: a design with twice the paper's tolerances runs what the
    paper's budget compiled (nothing traced or lowered again), with twice the position σ
    (first order, σ is linear in the tolerances) and half the tolerance cost (Σ paper / t
    over the six sources: 6 at the paper's budget, 3 at twice it)."""
    paper = jt.assess_design(design, workspace=few_poses).values
    hw = jt.hardware_for(REF, tolerances=jt.Tolerances().scaled(2.0))
    with compiled_programs("jaxpr_to_mlir_module") as lowered:
        loose = jt.assess_design(jt.Design(design.geometry, hw), workspace=few_poses).values
    assert lowered == [], lowered
    assert float(paper["tolerance_cost"]) == pytest.approx(6.0, rel=1e-12)
    assert float(loose["tolerance_cost"]) == pytest.approx(3.0, rel=1e-12)
    for k in ("max_position_sigma_mm", "max_rotation_sigma_arcsec"):
        assert float(loose[k]) == pytest.approx(2.0 * float(paper[k]), rel=1e-12), k
    assert float(loose["gci"]) == float(paper["gci"])  # geometry alone


def test_stacks_of_any_size_share_few_compiled_programs(design):
    """`assess_designs` runs stacks of up to 64 designs as the next power of two (at least
    8; `run_batch`'s sizes, counted in test_batch) and larger ones in whole chunks of 64:
    stacks of 3 and 70 designs compile two programs (8 and 64 designs), then 5 and 130
    designs compile nothing. Every design's criteria equal `design_criteria` of that design
    alone, the last one of each stack (repeated as padding) included."""
    poses = jnp.asarray(jt.design_poses(None, n_sweep=5, n_random=16, box=2))  # as below
    heights = {n: np.linspace(450.0, 850.0, n) for n in (3, 70, 5, 130)}
    out = {}
    with compiled_programs() as compiles:
        for n, hs in heights.items():
            if n == 5:
                assert compiles.count("jit(_vmap__design_row)") == 2, compiles
            out[n] = jt.assess_designs(
                stack([set_values(design, {"home_height": h}) for h in hs]), poses
            )
    assert compiles.count("jit(_vmap__design_row)") == 2, compiles
    for n in (3, 70, 130):
        for i in (0, n // 2, n - 1):
            d = set_values(design, {"home_height": heights[n][i]})
            one = jt.design_criteria(d.table(), d.hardware, poses)
            for k, v in one.items():
                assert out[n][k].shape == (n,)
                np.testing.assert_allclose(out[n][k][i], float(v), rtol=1e-12, err_msg=k)


def test_gradient_optimum_matches_a_brute_force_grid(design):
    poses = jt.design_poses(None, n_sweep=5, n_random=16, box=2)
    names = ("home_height", "platform_radius")
    lo, hi = np.array([400.0, 200.0]), np.array([900.0, 520.0])
    r = jt.optimize_design(
        design,
        list(names),
        "gci",
        workspace=poses,
        bounds={n: (lo[i], hi[i]) for i, n in enumerate(names)},
        starts=3,
    )
    n = 41
    A, B = np.meshgrid(np.linspace(lo[0], hi[0], n), np.linspace(lo[1], hi[1], n), indexing="ij")
    grid = stack(
        [set_values(design, {names[0]: x, names[1]: y}) for x, y in zip(A.ravel(), B.ravel())]
    )
    g = jt.assess_designs(grid, poses)["gci"]
    best = int(np.argmax(g))
    step = (hi - lo) / (n - 1)
    found = np.array([r.variables[names[0]][1], r.variables[names[1]][1]])
    assert r.value >= g[best] - 1e-9  # at least as good as the best grid point
    assert np.all(np.abs(found - [A.ravel()[best], B.ravel()[best]]) <= 1.5 * step)
    assert np.all((found > lo + step) & (found < hi - step))  # an interior optimum
    assert r.value > r.start_value


def test_reverse_mode_gradient_reaches_the_forward_mode_optimum(design, monkeypatch):
    # few variables take the loss's gradient in forward mode, many in reverse mode
    # (`gradient_mode`): both are the same gradient, so BFGS takes the same path
    from jaxtable._design import optimize

    assert optimize.gradient_mode(2) == "fwd"
    assert optimize.gradient_mode(optimize.FORWARD_UP_TO + 1) == "bwd"
    poses = jt.design_poses(None, n_sweep=5, n_random=16, box=2)
    names = ["home_height", "platform_radius"]
    bounds = {"home_height": (400.0, 900.0), "platform_radius": (200.0, 520.0)}
    fwd = jt.optimize_design(design, names, "gci", workspace=poses, bounds=bounds, starts=2)
    monkeypatch.setattr(optimize, "FORWARD_UP_TO", 0)
    assert optimize.gradient_mode(2) == "bwd"
    bwd = jt.optimize_design(design, names, "gci", workspace=poses, bounds=bounds, starts=2)
    assert bwd.value == pytest.approx(fwd.value, rel=1e-9)
    for n in names:
        assert bwd.variables[n][1] == pytest.approx(fwd.variables[n][1], rel=1e-6)
    assert fwd.value > fwd.start_value + 0.01  # it moved: the gradient did something


def test_discrete_enumeration_matches_exhaustive_search(design):
    poses = jt.design_poses(None, n_sweep=5, n_random=16, box=2)
    r = jt.optimize_design(design, ["hand"], "max_spiral_error_mm", workspace=poses)
    values = []
    for hand in np.array(np.meshgrid(*[[1.0, -1.0]] * 6, indexing="ij")).reshape(6, -1).T:
        a = jt.assess_design(set_values(design, {"hand": hand}), workspace=poses)
        values.append(a.values["max_spiral_error_mm"])
    assert r.value == pytest.approx(min(values), rel=1e-12)
    assert r.value < r.start_value  # mixing hands beats six right-hand screws
    # the lead catalogue: the spiral error is proportional to the lead (to the ~0.1 % the
    # spiral adds to the Jacobian), so the smallest lead wins
    r = jt.optimize_design(
        design, ["lead"], "max_spiral_error_mm", workspace=poses, lead_catalogue=[5, 10, 12.7, 16]
    )
    assert r.variables["lead"][1] == pytest.approx(np.full(6, 5.0))
    assert r.value == pytest.approx(r.start_value * 5 / 12.7, rel=1e-2)


def test_constraint_is_met_and_binds(design):
    # gci alone peaks inside the bounds; the first frequency grows towards a low, wide
    # platform (the corner 400 mm, 520 mm): asking for more frequency than the gci optimum
    # has must move the design to the constraint's boundary.
    poses = jt.design_poses(None, n_sweep=5, n_random=16, box=2)
    names = ["home_height", "platform_radius"]
    bounds = {"home_height": (400.0, 900.0), "platform_radius": (200.0, 520.0)}
    free = jt.optimize_design(design, names, "gci", workspace=poses, bounds=bounds, starts=2)
    corner = set_values(design, {"home_height": 400.0, "platform_radius": 520.0})
    f_max = jt.assess_design(corner, workspace=poses).values["first_frequency_Hz"]
    f_free = free.optimum.values["first_frequency_Hz"]
    assert f_max > f_free + 5.0
    limit = 0.5 * (f_free + f_max)
    con = jt.parse_constraint(f"first_frequency_Hz>={limit}")
    r = jt.optimize_design(design, names, "gci", [con], workspace=poses, bounds=bounds, starts=2)
    assert r.feasible and r.constraints[0]["met"]
    assert r.optimum.values["first_frequency_Hz"] >= limit * (1 - 1e-6)
    assert r.optimum.values["first_frequency_Hz"] == pytest.approx(limit, rel=0.01)  # it binds
    assert r.value < free.value  # the constraint costs dexterity
    assert r.value > free.value - 0.2  # ... but the optimiser still found a good design
    # a tighter limit binds too, and runs the program the first limit compiled: the limits,
    # bounds and poses are arguments of the optimiser's program, not constants in it
    traced = []

    def listen(event, duration, fun_name="?", **kw):
        if event == "/jax/core/compile/jaxpr_trace_duration":
            traced.append(fun_name)

    tight = 0.25 * f_free + 0.75 * f_max
    con = jt.parse_constraint(f"first_frequency_Hz>={tight}")
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        r2 = jt.optimize_design(
            design, names, "gci", [con], workspace=poses, bounds=bounds, starts=2
        )
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert not [n for n in traced if "round" in n or "criteria" in n], traced
    assert r2.feasible and r2.optimum.values["first_frequency_Hz"] == pytest.approx(tight, rel=0.01)
    assert r2.value < r.value


def test_a_hardware_variable_moves_to_where_its_constraint_binds(design):
    """A tolerance (a hardware variable) is cheapest at its loosest, so under a limit on
    the worst position σ it must go to where σ reaches the limit: that tolerance found
    independently, by bisection of the exact σ in the tolerance (σ grows with it). The
    optimiser once evaluated the criteria with the start's hardware, so a hardware
    variable had no gradient and came back at its start."""
    from scipy.optimize import brentq

    poses = jt.design_poses(None, n_sweep=3, n_random=8, box=2)
    name = "tolerances.base_joints"
    paper = float(design.hardware.tolerances.base_joints)
    bounds = {name: (0.1 * paper, 10 * paper)}

    def sigma(t):
        d = design.replace({name: t})
        return jt.assess_design(d, workspace=poses).values["max_position_sigma_mm"]

    limit = 1.2 * sigma(paper)
    t_star = brentq(lambda t: sigma(t) - limit, paper, 10 * paper, xtol=1e-9 * paper)
    con = jt.parse_constraint(f"max_position_sigma_mm<={limit}")
    r = jt.optimize_design(
        design, [name], "tolerance_cost", [con], workspace=poses, bounds=bounds, starts=2
    )
    start, found = r.variables[name]
    assert start == pytest.approx(paper) and r.feasible and r.constraints[0]["met"]
    assert r.optimum.values["max_position_sigma_mm"] == pytest.approx(limit, rel=0.005)
    assert found == pytest.approx(t_star, rel=0.005), (found, t_star)
    assert r.value < r.start_value


# ---------------------------------------------------------------- bad input


def test_designs_outside_physical_limits_are_refused_with_the_variable_named(design):
    with pytest.raises(jt.TableFileError, match="base_radius"):
        jt.assess_design(set_values(design, {"base_radius": -10.0}))
    with pytest.raises(jt.TableFileError, match="stroke"):
        jt.assess_design(set_values(design, {"stroke": jnp.array([900.0, 800.0])}))
    with pytest.raises(jt.TableFileError, match="platform_half_angle"):
        jt.assess_design(set_values(design, {"platform_half_angle": 1.2}))
    with pytest.raises(jt.TableFileError, match="leg_stiffness"):
        jt.hardware_for(REF, leg_stiffness=-1.0)
    with pytest.raises(jt.TableFileError, match="workspace"):
        far = np.tile([0.0, 0.0, 900.0, 0, 0, 0], (5, 1))
        jt.assess_design(design, workspace=far)
    with pytest.raises(ValueError, match="unknown design variable 'radius'"):
        jt.optimize_design(design, ["radius"], "gci")
    with pytest.raises(ValueError, match="not a criterion"):
        jt.optimize_design(design, ["home_height"], "stiffness")
    with pytest.raises(ValueError, match="NAME<=VALUE"):
        jt.parse_constraint("max_leg_force_N < 3")
    with pytest.raises(ValueError, match="outside its bounds"):
        jt.optimize_design(design, ["home_height"], "gci", bounds={"home_height": (100, 200)})


def test_a_table_that_is_not_symmetric_is_refused_as_one():
    t = jt.replace(REF, base_joints=REF.base_joints.at[2, 0].add(1.0))
    with pytest.raises(jt.TableFileError, match="not a symmetric hexapod"):
        jt.SymmetricDesign.from_table(t)
    # ... and its own leaves remain design variables
    d = jt.Design(t, jt.hardware_for(t))
    assert float(jt.assess_design(d, workspace=np.zeros((1, 6))).values["coverage"]) == 1.0


def test_workspace_files_name_the_bad_row_and_column(tmp_path):
    p = tmp_path / "ws.csv"
    p.write_text("x,y,z,roll,pitch,yaw\n0,0,0,0,0,0\n1,2,three,0,0,0\n")
    with pytest.raises(jt.WorkspaceFileError, match="row 2, column 'z'"):
        jt.load_workspace(p)
    p.write_text("cmd_x,cmd_y,cmd_z,cmd_roll,cmd_pitch,cmd_yaw\n10,0,0,0,0,90\n")
    pl = jt.load_workspace(p)
    np.testing.assert_allclose(pl.poses(), [[10, 0, 0, 0, 0, math.pi / 2]])
    t = tmp_path / "ws.toml"
    t.write_text("single = [100, 100, 50, 10, 10]\n")
    with pytest.raises(jt.WorkspaceFileError, match="'single' must be 6 numbers"):
        jt.load_workspace(t)
    t.write_text("single = [100, 100, 50, 10, 10, 10]\n")
    assert jt.load_workspace(t).single == (100, 100, 50, 10, 10, 10)


# ---------------------------------------------------------------- command line


def test_cli_design_evaluate_writes_every_key(tmp_path):
    from jaxtable.cli import main

    out = tmp_path / "ev"
    rc = main(["design", "evaluate", "--out", str(out), "--n-sweep", "5", "--n-random", "16"])
    assert rc == 0
    doc = json.loads((out / "design.json").read_text())
    keys = [
        "coverage",
        "gci",
        "min_lci",
        "max_position_sigma_mm",
        "max_rotation_sigma_arcsec",
        "max_spiral_error_mm",
        "min_stiffness_translation_N_per_mm",
        "stiffness_home",
        "max_leg_force_N",
        "max_motor_rpm",
        "first_frequency_Hz",
    ]
    assert all(k in doc for k in keys)
    K = np.array(doc["stiffness_home"])
    assert K.shape == (6, 6) and np.allclose(K, K.T, rtol=1e-9, atol=1e-6)
    assert (out / "design_sweeps.png").exists()
    with pytest.raises(SystemExit) as stop:  # the parser refuses it, naming the option
        main(["design", "evaluate", "--out", str(out), "--leg-stiffness", "-5"])
    assert stop.value.code == 2


def test_cli_design_optimize_writes_a_table_and_the_contract(tmp_path):
    from jaxtable.cli import main

    out = tmp_path / "opt"
    rc = main(
        [
            "design",
            "optimize",
            "--vary",
            "hand",
            "--objective",
            "max_spiral_error_mm",
            "--constraint",
            "max_leg_force_N<=5000",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    doc = json.loads((out / "design_optimize.json").read_text())
    for k in ("objective", "start_value", "value", "design", "constraints"):
        assert k in doc
    assert doc["value"] < doc["start_value"]
    assert doc["constraints"][0]["name"] == "max_leg_force_N" and doc["constraints"][0]["met"]
    t = jt.load_table(out / "design.toml")
    np.testing.assert_array_equal(np.asarray(t.hand), doc["design"]["hand"])
    rc = main(["design", "optimize", "--vary", "hand", "--objective", "nope", "--out", str(out)])
    assert rc == 2


@pytest.mark.slow
def test_pareto_front_is_non_dominated_and_spans_the_two_optima(design, tmp_path):
    poses = jt.design_poses(None, n_sweep=5, n_random=16, box=2)
    names = ["home_height", "platform_radius"]
    bounds = {"home_height": (400.0, 900.0), "platform_radius": (200.0, 520.0)}
    front = jt.pareto_front(
        design,
        names,
        "gci",
        "first_frequency_Hz",
        workspace=poses,
        bounds=bounds,
        starts=2,
        n_points=5,
    )
    pts = front.points
    assert len(pts) >= 3
    g = np.array([p["gci"] for p in pts])
    f = np.array([p["first_frequency_Hz"] for p in pts])
    # sorted by the second criterion from worst to best, the first must fall: a trade-off
    assert np.all(np.diff(f) <= 1e-9) and np.all(np.diff(g) >= -1e-9)
    a, b = front.ends
    assert g.max() == pytest.approx(a.value, rel=1e-3)
    assert f.max() == pytest.approx(b.value, rel=1e-3)
    front.to_csv(tmp_path / "front.csv")
    lines = (tmp_path / "front.csv").read_text().splitlines()
    assert lines[0].split(",")[:3] == ["epsilon", "gci", "first_frequency_Hz"]
    assert len(lines) == len(pts) + 1


def test_leg_stiffness_defaults_to_a_fitted_compliance():
    eff = {"compliance": jt.Compliance.from_k([1e4, 2e4, 3e4, 4e4, 5e4, 6e4])}
    hw = jt.hardware_for(REF, effects=eff)
    np.testing.assert_allclose(np.asarray(hw.leg_stiffness), [1e4, 2e4, 3e4, 4e4, 5e4, 6e4])
    rigid = jt.hardware_for(REF, effects={"compliance": jt.Compliance(0.0)})
    np.testing.assert_allclose(np.asarray(rigid.leg_stiffness), 2e4)
