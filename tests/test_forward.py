"""Forward kinematics: round trips, compensation, implicit gradients, failures named."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import compiled_programs, quick_jit, random_poses

import jaxtable as jt
from jaxtable import _kinematics as kin

TOL_MM, TOL_RAD = 1e-9, 1e-10


def assert_pose_close(q, p):
    err = np.abs(np.asarray(q) - np.asarray(p))
    assert err[..., :3].max() < TOL_MM, err[..., :3].max()
    assert err[..., 3:].max() < TOL_RAD, err[..., 3:].max()


@pytest.fixture(scope="module")
def poses():
    return random_poses(10_000, seed=11)


def test_round_trip_rigid(table, poses):
    cmd = jt.actuator_command(table, poses, compensated=False)
    np.testing.assert_array_equal(np.asarray(cmd), np.asarray(jt.leg_lengths(table, poses)))
    assert_pose_close(jt.forward(table, cmd, effects={}), poses)


def test_round_trip_with_spiral(table, poses):
    cmd = jt.actuator_command(table, poses, compensated=True)
    # the command differs from the rigid one by exactly the passive extension
    np.testing.assert_allclose(
        np.asarray(cmd),
        np.asarray(jt.leg_lengths(table, poses)) - np.asarray(jt.spiral_extension(table, poses)),
        atol=1e-12,
    )
    assert_pose_close(jt.forward(table, cmd), poses)  # hardware effects: spiral inside


def test_compensation_lands_on_pose_and_uncompensated_does_not(table):
    line = np.zeros((17, 6))
    line[:, 0] = np.linspace(-200, 200, 17)
    comp = jt.forward(table, jt.actuator_command(table, line, compensated=True))
    assert_pose_close(comp, line)
    raw = np.asarray(jt.forward(table, jt.actuator_command(table, line, compensated=False)))
    err = raw - line
    assert np.abs(err[:, :3]).max() > 0.05  # the passive term moves the platform (mm)
    # first order, the error is the paper's eq. (21): Δq = J⁻¹ Δl2 (Euler increments)
    jac = quick_jit(jax.jacfwd(lambda q: kin.leg_lengths(table, q)))
    for k in (0, 4, 12, 16):
        J = np.asarray(jac(line[k]))
        dl2 = np.asarray(jt.spiral_extension(table, line[k]))
        lin = np.linalg.solve(J, dl2)
        np.testing.assert_allclose(err[k], lin, atol=1e-2 * np.abs(lin).max() + 1e-12)


def test_s_dependent_effect_uses_newton_inverse(table):
    class Scale(jt.AbstractEffect):
        eps: jax.Array
        depends_on_extension = True

        def __call__(self, table, pose, s, ctx=None):
            return self.eps * s + 0.01 * jnp.sin(s / 5.0)

    eff = {"scale": Scale(jnp.full(6, 8.3e-5 * 50)), **jt.default_effects(table)}
    poses = random_poses(200, seed=2)
    cmd = jt.actuator_command(table, poses, effects=eff)
    s = np.asarray(cmd) - np.asarray(table.zero_lengths)
    # the defining equation holds: |l| = L0 + s + spiral + eps s + 0.01 sin(s/5)
    rhs = (
        np.asarray(table.zero_lengths)
        + s
        + np.asarray(jt.spiral_extension(table, poses))
        + 8.3e-5 * 50 * s
        + 0.01 * np.sin(s / 5.0)
    )
    np.testing.assert_allclose(np.asarray(jt.leg_lengths(table, poses)), rhs, atol=1e-10)
    assert_pose_close(jt.forward(table, cmd, effects=eff), poses)


def test_forward_gradient_matches_finite_differences(table):
    pose = random_poses(1, seed=12)[0]
    cmd = np.asarray(jt.actuator_command(table, pose))

    def f(c):
        return jt.forward(table, c)

    J = np.asarray(quick_jit(jax.jacfwd(f))(jnp.asarray(cmd)))  # eagerly: ~40 programs
    h = 1e-4
    Jfd = np.stack(
        [(np.asarray(f(cmd + h * e)) - np.asarray(f(cmd - h * e))) / (2 * h) for e in np.eye(6)],
        -1,
    )
    np.testing.assert_allclose(J, Jfd, rtol=1e-6, atol=1e-11)

    # and equals the inverse of d(actuator length)/d(pose) (implicit function theorem)
    def g(q):
        return kin.leg_lengths(table, q) - kin.spiral_extension(table, q)

    np.testing.assert_allclose(
        J, np.linalg.inv(np.asarray(quick_jit(jax.jacfwd(g))(pose))), rtol=1e-9, atol=1e-14
    )


@pytest.mark.parametrize("chord_below", [None, 1e-3])
def test_implicit_derivative_is_the_inverse_command_jacobian(table, chord_below):
    """d pose / d extension through one solve from home, forward and reverse mode, = the
    inverse of d(command)/d(pose) (implicit function theorem, from the kinematics alone):
    without a chord phase the derivative reuses the Newton solve's last factorisation, with
    one (its factorisation up to 1e-3 of the platform radius away) it takes the Jacobian at
    the solution; both to 1e-9."""
    from jaxtable._forward import forward_one

    pose = np.array([120.0, -60.0, 30.0, 0.06, -0.04, 0.1])
    s = jnp.asarray(jt.actuator_command(table, pose) - np.asarray(table.zero_lengths))
    opts = jt.ForwardOptions(chord_below=chord_below)
    eff = {"spiral": jt.Spiral.from_table(table)}

    def f(x):
        return forward_one(table, eff, x, jnp.zeros(6), opts)[0]

    # each under one jit: eagerly, the solve's loop and every op around it compile apart
    q, result, steps, _ = quick_jit(lambda x: forward_one(table, eff, x, jnp.zeros(6), opts))(s)
    assert result == jt.RESULTS.successful and int(steps) >= 4  # several steps from home
    np.testing.assert_allclose(np.asarray(q), pose, atol=1e-9)

    def g(p):
        return kin.leg_lengths(table, p) - kin.spiral_extension(table, p)

    truth = np.linalg.inv(np.asarray(quick_jit(jax.jacfwd(g))(pose)))
    for J in (quick_jit(jax.jacfwd(f))(s), quick_jit(jax.jacrev(f))(s)):
        np.testing.assert_allclose(np.asarray(J), truth, rtol=1e-9, atol=1e-14)


def test_forward_gradient_wrt_table_parameters(table):
    """d pose / d lead through the solve (implicit diff) = finite differences."""
    pose = np.array([-150.0, 40.0, 10.0, 0.05, -0.03, 0.08])
    cmd = jt.actuator_command(table, pose, compensated=False)

    def f(lead):
        t = jt.replace(table, lead=lead)
        return jt.forward(t, cmd)

    lead = np.asarray(table.lead)
    J = np.asarray(quick_jit(jax.jacfwd(f))(jnp.asarray(lead)))
    h = 1e-3
    Jfd = np.stack(
        [(np.asarray(f(lead + h * e)) - np.asarray(f(lead - h * e))) / (2 * h) for e in np.eye(6)],
        -1,
    )
    np.testing.assert_allclose(J, Jfd, rtol=1e-5, atol=1e-12)
    assert np.abs(J).max() > 1e-3


# --- bad input ------------------------------------------------------------------------------


def test_nan_pose_is_named(table):
    poses = random_poses(5, seed=1)
    poses[3, 4] = np.nan
    for fn in (jt.leg_lengths, jt.rod_rotation, jt.spiral_extension, jt.actuator_command):
        with pytest.raises(jt.KinematicsError, match=r"pose \[3\]: non-finite pitch"):
            fn(table, poses)


def test_pose_outside_stroke_is_named(table):
    poses = np.zeros((2, 3, 6))
    poses[1, 2, 2] = 450.0  # 450 mm up: every leg past the 1060 mm stroke end
    with pytest.raises(jt.KinematicsError) as e:
        jt.actuator_command(table, poses)
    msg = str(e.value)
    assert "pose [1, 2]" in msg and "leg 1" in msg and "outside stroke [600.0, 1060.0]" in msg
    assert "pose [0, 0]" not in msg


def test_reachable_and_joint_limits(table):
    line = np.zeros((3, 6))
    line[:, 0] = [-200, 0, 200]
    assert np.asarray(jt.reachable(table, line)).all()
    jt.check_reachable(table, line)
    tilt = np.zeros(6)
    tilt[3] = np.deg2rad(40)  # roll 40 deg: beyond the 35 deg U-joint limit
    assert not bool(jt.reachable(table, tilt))
    with pytest.raises(jt.KinematicsError, match="joint bend .* > limit 35.00 deg"):
        jt.check_reachable(table, tilt)


def test_reachable_against_numpy_geometry_near_the_joint_limit(table):
    """`reachable` (bend compared as a cosine) against the bends computed here from the
    joint positions with numpy (arccos of unit leg directions, base frame and platform frame,
    from home): poses tilted up to 45° cross the 35° limit; a pose within 1e-9 rad of it
    is not compared. With an infinite limit only the stroke decides."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(11)
    poses = np.zeros((400, 6))
    poses[:, :3] = rng.uniform(-60, 60, (400, 3))
    poses[:, 3:] = rng.uniform(-1, 1, (400, 3)) * np.deg2rad([45, 45, 30])
    a, b = np.asarray(table.platform_joints), np.asarray(table.base_joints)
    home = np.array([0, 0, float(table.home_height)])

    def legs(p):
        R = Rotation.from_euler("ZYX", p[::-1][:3]).as_matrix()
        return home + p[:3] + a @ R.T - b, R

    l0, _ = legs(np.zeros(6))
    u0 = l0 / np.linalg.norm(l0, axis=1, keepdims=True)
    bend, length = [], []
    for p in poses:
        l, R = legs(p)
        u = l / np.linalg.norm(l, axis=1, keepdims=True)
        ang = lambda x: np.arccos(np.clip(np.sum(x * u0, axis=1), -1, 1))  # noqa: E731
        bend.append(np.maximum(ang(u), ang(u @ R)))
        length.append(np.linalg.norm(l, axis=1))
    bend, length = np.array(bend), np.array(length)
    lo, hi = np.asarray(table.stroke)
    in_stroke = ((length >= lo) & (length <= hi)).all(1)
    limit = float(table.joint_angle_limit)
    expected = in_stroke & (bend <= limit).all(1)
    clear = np.abs(bend - limit).min(1) > 1e-9
    assert 50 < expected.sum() < 350 and (in_stroke & ~expected).sum() > 50  # both rules bite
    got = np.asarray(jt.reachable(table, poses))
    np.testing.assert_array_equal(got[clear], expected[clear])
    free = jt.replace(table, joint_angle_limit=np.inf)
    np.testing.assert_array_equal(np.asarray(jt.reachable(free, poses)), in_stroke)


def test_forward_refuses_commands_outside_stroke(table):
    cmd = np.full((4, 6), 820.0)
    cmd[2, 5] = 1200.0
    with pytest.raises(jt.KinematicsError, match=r"pose \[2\]: leg 6 1200.000 mm outside stroke"):
        jt.forward(table, cmd)


def test_forward_reports_unsolvable_command(table):
    """Alternate legs at opposite stroke ends: each length is inside the stroke but no pose
    fits all six; the failure is named, not returned as NaN."""
    cmd = np.full((3, 6), float(table.zero_lengths[0]))
    cmd[1] = [600.0, 1060.0, 600.0, 1060.0, 600.0, 1060.0]
    with pytest.raises(jt.KinematicsError) as e:
        jt.forward(table, cmd)
    msg = str(e.value)
    assert "pose [1]" in msg and "pose [0]" not in msg and "pose [2]" not in msg
    res = jt.forward_solve(table, cmd)
    assert np.asarray(res.ok).tolist() == [True, False, True]


def test_forward_inside_jit_raises_through_error_if(table):
    cmd = np.full((2, 6), float(table.zero_lengths[0]))
    cmd[1] = [600.0, 1060.0, 600.0, 1060.0, 600.0, 1060.0]
    f = eqx.filter_jit(lambda c: jt.forward(table, c))
    with pytest.raises(Exception, match="forward kinematics failed"):
        jax.block_until_ready(f(jnp.asarray(cmd)))


def test_non_finite_command_is_named(table):
    cmd = np.full((2, 6), 820.0)
    cmd[0, 2] = np.inf
    with pytest.raises(jt.KinematicsError, match=r"pose \[0\]: non-finite length on leg 3"):
        jt.forward(table, cmd)


def test_float64_is_on():
    assert jax.config.jax_enable_x64
    assert jt.leg_lengths(jt.reference_table(), np.zeros(6)).dtype == jnp.float64


def test_reverse_mode_through_forward(table):
    """jax.grad (reverse mode) through the solve = forward-mode jacobian."""
    pose = np.array([-150.0, 40.0, 10.0, 0.05, -0.03, 0.08])
    cmd = jt.actuator_command(table, pose, compensated=False)

    def f(lead):
        return jnp.sum(jt.forward(jt.replace(table, lead=lead), cmd) * jnp.arange(1.0, 7.0))

    # each under one jit: eagerly, grad and jacfwd ran the solve's pieces as ~40 programs
    g = np.asarray(quick_jit(jax.grad(f))(table.lead))
    np.testing.assert_allclose(g, np.asarray(quick_jit(jax.jacfwd(f))(table.lead)), rtol=1e-10)
    assert np.abs(g).max() > 1e-3


def test_failed_solve_returns_guess_not_nan(table):
    res = jt.forward_solve(table, np.array([[600.0, 1060.0, 600.0, 1060.0, 600.0, 1060.0]]))
    assert not bool(res.ok[0]) and np.all(np.isfinite(np.asarray(res.pose)))


@pytest.mark.parametrize("effects", [None, {"lead_scale": "s-dependent"}])
def test_first_step_for_the_batch_changes_nothing(table, effects):
    """A guess shared by the batch takes its first Newton step before the loop (its Jacobian
    once for the batch): poses, step counts and results equal those of the same guess given
    per row, successes and failures alike, with and without an effect that depends on s
    (whose Jacobian stays per pose). (The default on large batches; asked for here.)"""
    if effects is not None:
        effects = {"spiral": jt.Spiral.from_table(table), "lead_scale": jt.LeadScale(2e-4)}
    cmd = np.array(jt.actuator_command(table, random_poses(300, seed=12)))
    cmd[7] = [600.0, 1060.0, 600.0, 1060.0, 600.0, 1060.0]  # no pose fits: a failure
    cmd[8] = np.asarray(table.zero_lengths)  # home: converges at the first step
    peel = jt.ForwardOptions(peel_first_step=True)
    shared = jt.forward_solve(table, cmd, effects=effects, options=peel)
    per_row = jt.forward_solve(table, cmd, effects=effects, guess=np.zeros((len(cmd), 6)))
    np.testing.assert_allclose(np.asarray(shared.pose), np.asarray(per_row.pose), atol=1e-12)
    np.testing.assert_array_equal(np.asarray(shared.steps), np.asarray(per_row.steps))
    assert np.all(np.asarray(shared.result == per_row.result))
    assert not bool(shared.ok[7]) and bool(shared.ok[8]) and int(shared.steps[8]) <= 2


@pytest.mark.parametrize("effects", [None, {"lead_scale": "s-dependent"}])
def test_chord_steps_land_where_newton_does(table, effects):
    """Batch forward kinematics switches to chord steps (the last factorisation reused) once
    a Newton step is below 1e-3 of the platform radius (the default on large batches, asked
    for here): the same poses as Newton's to the stopping rule's precision, the same
    successes and failures, round trips within 1e-9 mm, and the switch really happens
    (linear convergence: some poses need an extra step). With the switch far earlier (every
    step after the first from a home guess, chord steps with the home Jacobian across the
    whole workspace) the answers are still the same."""
    if effects is not None:
        effects = {"spiral": jt.Spiral.from_table(table), "lead_scale": jt.LeadScale(2e-4)}
    poses = random_poses(2000, seed=13)
    cmd = np.array(jt.actuator_command(table, poses, effects=effects))
    cmd[7] = [600.0, 1060.0, 600.0, 1060.0, 600.0, 1060.0]  # no pose fits: a failure
    cmd[8], poses[8] = np.asarray(table.zero_lengths), 0.0  # home
    newton = jt.forward_solve(
        table, cmd, effects=effects, options=jt.ForwardOptions(chord_below=0.0)
    )
    chord = jt.forward_solve(
        table, cmd, effects=effects, options=jt.ForwardOptions(chord_below=1e-3)
    )
    early = jt.forward_solve(
        table,
        cmd,
        effects=effects,
        guess=np.zeros((len(cmd), 6)),
        options=jt.ForwardOptions(chord_below=10.0),
    )
    ok = np.asarray(newton.ok)
    assert ok.sum() == len(cmd) - 1 and not ok[7]
    for r in (chord, early):
        assert np.all(np.asarray(r.result == newton.result))
        np.testing.assert_allclose(np.asarray(r.pose)[ok], np.asarray(newton.pose)[ok], atol=1e-10)
        assert_pose_close(np.asarray(r.pose)[ok], poses[ok])
    extra = np.asarray(chord.steps) - np.asarray(newton.steps)
    assert extra.min() >= 0 and (extra > 0).mean() > 0.05, np.bincount(extra - extra.min())
    assert np.asarray(early.steps)[ok].mean() > np.asarray(newton.steps)[ok].mean() + 3


def test_batch_size_chooses_the_newton_variant(table, monkeypatch):
    """`forward_solve`'s defaults: from `LARGE_BATCH` rows the peeled first step (shared
    guess only) and chord steps below `CHORD_BELOW`; under it plain Newton steps, whatever
    the guess; options the caller sets are kept as they are. The small batch's default
    gives exactly what plain Newton asked for explicitly gives."""
    from jaxtable import _api
    from jaxtable._forward import CHORD_BELOW
    from jaxtable._jit import LARGE_BATCH

    seen = []

    def spy(fn, shared, batched, **kw):
        seen.append(shared[2])
        raise StopIteration  # the decision is all this test reads

    monkeypatch.setattr(_api, "run_batch", spy)
    one = np.asarray(table.zero_lengths)
    cases = [
        (LARGE_BATCH, None, {}, (True, CHORD_BELOW)),
        (LARGE_BATCH, "rows", {}, (False, CHORD_BELOW)),
        (LARGE_BATCH - 1, None, {}, (False, 0.0)),
        (LARGE_BATCH - 1, "rows", {}, (False, 0.0)),
        (10, None, dict(peel_first_step=True, chord_below=2e-3), (True, 2e-3)),
        (LARGE_BATCH, None, dict(peel_first_step=False, chord_below=0.0), (False, 0.0)),
    ]
    for n, guess, options, _ in cases:
        g = np.zeros((n, 6)) if guess == "rows" else None
        with pytest.raises(StopIteration):
            jt.forward_solve(
                table, np.tile(one, (n, 1)), guess=g, options=jt.ForwardOptions(**options)
            )
    assert [(o.peel_first_step, o.chord_below) for o in seen] == [c[-1] for c in cases]
    monkeypatch.undo()
    cmd = np.asarray(jt.actuator_command(table, random_poses(50, seed=3)))
    default = jt.forward_solve(table, cmd)
    plain = jt.forward_solve(
        table, cmd, options=jt.ForwardOptions(peel_first_step=False, chord_below=0.0)
    )
    np.testing.assert_array_equal(np.asarray(default.pose), np.asarray(plain.pose))
    np.testing.assert_array_equal(np.asarray(default.steps), np.asarray(plain.steps))


def test_chord_step_that_would_not_halve_is_not_taken():
    """The chord phase on r(y) = sinh(y) − sinh(y*) per component from y = 0 with the switch
    right after the first step: when the reused slope cosh(0) = 1 cannot reach the root
    (y* = 2: the chord step from y₁ = sinh(2) would be sinh(3.63) − 3.63 ≈ 15 > y₁/2) the
    step is refused and the pose left, unconverged, for the Newton loop; near the root
    (y* = 0.05) the chord steps converge to it."""
    from jaxtable._forward import _chord_phase
    from jaxtable._linalg import lu_small, lu_solve_small

    def run(target):
        b = np.sinh(np.full(6, target))

        def fn(y):
            r = jnp.sinh(y) - b
            return r, r

        def converged(y_new, dy, r):
            return (jnp.max(jnp.abs(dy)) < 1e-12) & (jnp.max(jnp.abs(r)) < 1e-12)

        def cond(c):
            return ~c[2] & (c[1] < 50)

        def newton_step(y):
            r = fn(y)[0]
            J = jnp.diag(jnp.cosh(y))  # d sinh(y)/dy, per component
            LU, perm = lu_small(J)
            dy = lu_solve_small(LU, perm, r[:, None])[:, 0]
            return y - dy, dy, r, LU, perm

        start = (jnp.zeros(6), jnp.array(0), False)
        return _chord_phase(fn, newton_step, converged, start, cond, 1e9)

    y, k, done = run(2.0)
    np.testing.assert_allclose(np.asarray(y), np.sinh(2.0), rtol=1e-14)  # Newton step 1 only
    assert int(k) == 1 and not bool(done)
    y, k, done = run(0.05)
    np.testing.assert_allclose(np.asarray(y), 0.05, rtol=1e-12)
    assert bool(done) and int(k) > 3  # linear convergence: more steps than Newton's ~4


def test_small_batches_run_one_kernel_whatever_the_kind_of_guess_and_context(table):
    """Under `LARGE_BATCH` rows a shared guess or context is taken per row: a batch from
    home in the home context, one with a guess per row and one with a context per row run
    the same compiled kernel, and commands likewise; the poses are those of the shared
    inputs, exactly."""
    poses = random_poses(20, seed=5) / 2
    ctx = jt.Context(temperature=np.full(20, 20.0))  # per row, the home temperature
    with compiled_programs():
        cmd = np.asarray(jt.actuator_command(table, poses))
        a = jt.forward_solve(table, cmd)  # shared guess (home) and context
    with compiled_programs() as later:
        cmd_rows = np.asarray(jt.actuator_command(table, poses, context=ctx))
        b = jt.forward_solve(table, cmd, guess=np.zeros((20, 6)))
        c = jt.forward_solve(table, cmd, context=ctx)
    assert not [p for p in later if "_row" in p], later
    np.testing.assert_array_equal(cmd_rows, cmd)
    for r in (b, c):
        np.testing.assert_array_equal(np.asarray(r.pose), np.asarray(a.pose))
    assert np.all(np.asarray(a.ok))
    np.testing.assert_allclose(np.asarray(a.pose), poses, atol=1e-9)
