"""Pose -> leg map: hand-computed lengths, rod rotation truths, gradients, the paper's form."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import quick_jit, random_poses, x_line

import jaxtable as jt
from jaxtable import _kinematics as kin

AZ = np.deg2rad([10, 110, 130, 230, 250, 350])


def simple_table(lead=0.0, hand=1.0, base_axes=None, platform_axes=None):
    """Base joints on r = 500 and platform joints on r = 300 at the same azimuths, h = 400."""
    ring = np.stack([np.cos(AZ), np.sin(AZ), np.zeros(6)], -1)
    tangent = np.stack([-np.sin(AZ), np.cos(AZ), np.zeros(6)], -1)
    return jt.Table(
        base_joints=500 * ring,
        platform_joints=300 * ring,
        base_axes=tangent if base_axes is None else base_axes,
        platform_axes=tangent if platform_axes is None else platform_axes,
        home_height=400.0,
        stroke=(100.0, 2000.0),
        lead=lead,
        hand=hand,
    )


def test_leg_lengths_hand_computed():
    t = simple_table()
    # home and pure heave: every leg sqrt(200^2 + (400 + z)^2)
    for z in (0.0, 100.0, -150.0):
        L = np.asarray(jt.leg_lengths(t, np.array([0, 0, z, 0, 0, 0.0])))
        np.testing.assert_allclose(L, np.hypot(200.0, 400.0 + z), rtol=0, atol=1e-12)
    # pure yaw: law of cosines in the horizontal plane
    psi = 0.3
    L = np.asarray(jt.leg_lengths(t, np.array([0, 0, 0, 0, 0, psi])))
    expect = np.sqrt(500**2 + 300**2 - 2 * 500 * 300 * np.cos(psi) + 400**2)
    np.testing.assert_allclose(L, expect, rtol=0, atol=1e-12)
    # pure surge: (300 - 500) cos(az) + x, (300 - 500) sin(az), 400
    x = 120.0
    L = np.asarray(jt.leg_lengths(t, np.array([x, 0, 0, 0, 0, 0.0])))
    expect = np.sqrt((-200 * np.cos(AZ) + x) ** 2 + (200 * np.sin(AZ)) ** 2 + 400**2)
    np.testing.assert_allclose(L, expect, rtol=0, atol=1e-12)
    # pure roll, leg with a joint at azimuth 90 deg written out by hand
    phi = 0.2
    t90 = jt.Table(
        base_joints=np.tile([0.0, 500.0, 0.0], (6, 1)),
        platform_joints=np.tile([0.0, 300.0, 0.0], (6, 1)),
        base_axes=np.tile([1.0, 0, 0], (6, 1)),
        platform_axes=np.tile([1.0, 0, 0], (6, 1)),
        home_height=400.0,
        stroke=(100.0, 2000.0),
    )
    L = np.asarray(jt.leg_lengths(t90, np.array([0, 0, 0, phi, 0, 0.0])))
    expect = np.hypot(300 * np.cos(phi) - 500, 400 + 300 * np.sin(phi))
    np.testing.assert_allclose(L, expect, rtol=0, atol=1e-12)


@pytest.mark.parametrize("shape", [(), (7,), (3, 4), (2, 1, 5)])
def test_batch_shapes(table, shape):
    poses = random_poses(int(np.prod(shape)), seed=3).reshape(shape + (6,))
    L = np.asarray(jt.leg_lengths(table, poses))
    assert L.shape == shape + (6,)
    flat = poses.reshape(-1, 6)
    one = np.stack([np.asarray(kin.leg_lengths(table, jnp.asarray(p))) for p in flat[:3]])
    np.testing.assert_allclose(L.reshape(-1, 6)[:3], one, atol=0)
    assert np.asarray(jt.rod_rotation(table, poses)).shape == shape + (6,)
    assert np.asarray(jt.joint_bend(table, poses)).shape == shape + (2, 6)


def test_chunked_batches_equal_one_vmap(table):
    poses = random_poses(1000, seed=4)
    a = np.asarray(jt.spiral_extension(table, poses))
    b = np.asarray(jt.spiral_extension(table, poses, chunk=64))  # 16 chunks, ragged tail
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-15)  # same maths, other fusion


def test_rod_rotation_zero_at_home(table):
    np.testing.assert_allclose(np.asarray(jt.rod_rotation(table, np.zeros(6))), 0.0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(jt.spiral_extension(table, np.zeros(6))), 0, atol=1e-15)


def test_mirror_pairs_antisymmetric_on_x_stroke(table):
    twist = np.asarray(jt.rod_rotation(table, x_line(np.linspace(-200, 200, 81))))
    for i, j in ((0, 5), (1, 4), (2, 3)):
        np.testing.assert_allclose(twist[:, i], -twist[:, j], atol=1e-14)
    assert np.abs(twist).max() > 0.1  # not trivially zero


def _about_leg_pose(table, leg, gamma):
    """Pose that turns the platform by `gamma` about leg `leg`'s own axis (a line through its
    two joints). The leg vector is unchanged, so the rod turns by exactly `gamma` relative to
    the barrel (right-hand about u)."""
    b = np.asarray(table.base_joints)[leg]
    ap = np.asarray(table.platform_joints)[leg]
    h = float(table.home_height)
    a0 = ap + [0, 0, h]
    u = (a0 - b) / np.linalg.norm(a0 - b)
    K = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
    R = np.eye(3) + np.sin(gamma) * K + (1 - np.cos(gamma)) * K @ K
    t = a0 - R @ ap  # keeps the platform joint in place
    roll = np.arctan2(R[2, 1], R[2, 2])
    pitch = -np.arcsin(R[2, 0])
    yaw = np.arctan2(R[1, 0], R[0, 0])
    return np.array([t[0], t[1], t[2] - h, roll, pitch, yaw])


@pytest.mark.parametrize("gamma_deg", [-179.0, -90.0, -7.0, 0.5, 45.0, 170.0, 179.5])
@pytest.mark.parametrize("leg", [0, 3])
def test_rod_rotation_equals_turn_about_leg_axis(table, leg, gamma_deg):
    pose = _about_leg_pose(table, leg, np.deg2rad(gamma_deg))
    L = np.asarray(jt.leg_lengths(table, pose))
    assert L[leg] == pytest.approx(float(table.zero_lengths[leg]), abs=1e-9)
    twist = np.asarray(jt.rod_rotation(table, pose))[leg]
    assert np.rad2deg(twist) == pytest.approx(gamma_deg, abs=1e-9)  # no wrap near ±180°


def test_spiral_extension_formula_and_hand():
    t_right = simple_table(lead=10.0, base_axes=None)
    pose = np.array([30.0, -20.0, 10.0, 0.05, -0.04, 0.1])
    twist = np.asarray(jt.rod_rotation(t_right, pose))
    ext = np.asarray(jt.spiral_extension(t_right, pose))
    np.testing.assert_allclose(ext, 10.0 * twist / (2 * np.pi), rtol=1e-15)
    t_mixed = simple_table(lead=[10.0, 10.0, 10.0, 10.0, 0.0, 10.0], hand=[1, -1, 1, -1, 1, 1])
    ext2 = np.asarray(jt.spiral_extension(t_mixed, pose))
    np.testing.assert_allclose(ext2, ext * np.array([1, -1, 1, -1, 0, 1]), rtol=1e-15)


def _central_jacobian(f, x, h):
    cols = []
    for k in range(x.size):
        e = np.zeros_like(x)
        e[k] = h[k]
        cols.append((np.asarray(f(x + e)) - np.asarray(f(x - e))) / (2 * h[k]))
    return np.stack(cols, -1)


@pytest.mark.parametrize("where", ["home", "random", "x_end"])
def test_rod_rotation_gradient_matches_central_differences(table, where):
    pose = {
        "home": np.zeros(6),
        "random": random_poses(1, seed=9)[0],
        "x_end": np.array([-200.0, 0, 0, 0, 0, 0]),
    }[where]
    f = jax.jit(lambda q: kin.rod_rotation(table, q))
    J = np.asarray(jax.jacfwd(f)(jnp.asarray(pose)))
    Jr = np.asarray(jax.jacrev(f)(jnp.asarray(pose)))
    assert np.all(np.isfinite(J))
    h = np.array([1e-3, 1e-3, 1e-3, 1e-6, 1e-6, 1e-6])
    Jfd = _central_jacobian(f, pose, h)
    np.testing.assert_allclose(J, Jfd, rtol=1e-6, atol=1e-10)
    np.testing.assert_allclose(Jr, J, rtol=1e-12, atol=1e-15)
    assert np.abs(J).max() > 1e-4  # the twist does respond to the pose


# --- the paper's literal form (eqs. 15-19) against the model ---------------------------------


def perpendicular_axes_table(home_twist_deg=0.0):
    """Table whose joint axes are perpendicular to the legs at home; the platform axis is
    turned by `home_twist_deg` from the base axis about the leg (0: k ∥ m at home)."""
    t = simple_table(lead=12.7)
    l0 = np.asarray(kin.leg_vectors(t, jnp.zeros(6)))
    u0 = l0 / np.linalg.norm(l0, axis=-1, keepdims=True)
    h = np.cross([0, 0, 1.0], u0)
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    g = np.deg2rad(home_twist_deg)
    j = np.cos(g) * h + np.sin(g) * np.cross(u0, h)
    return jt.replace(t, base_axes=h, platform_axes=j)


def test_paper_form_agrees_where_its_assumptions_hold():
    """Axes ⟂ legs at home, home twist 45° (arccos far from ±1), legs pointing up, small
    motion: the paper's form equals −model (its opposite sense) up to its second-order
    normalisation bias."""
    t = perpendicular_axes_table(45.0)
    unit = random_poses(50, seed=5, box=np.array([2, 2, 2, 0.002, 0.002, 0.002]))
    gaps, sizes = [], []
    for eps in (1.0, 0.1):
        ours = np.asarray(jt.rod_rotation(t, eps * unit))
        paper = np.asarray(jt.paper_rod_rotation(t, eps * unit))
        gaps.append(np.abs(paper + ours).max())
        sizes.append(np.abs(ours).max())
    assert gaps[0] < 0.05 * sizes[0]  # same first-order twist, opposite sense
    assert sizes[0] / sizes[1] == pytest.approx(10, rel=0.05)  # twist is first order
    assert gaps[0] / gaps[1] > 80  # the disagreement is second order


def test_paper_form_with_zero_home_twist_is_biased_at_small_motion():
    """With k ∥ m at home (α0 = 0) the |l| normalisation bias is first order: arccos of
    |n×u||j×u| cos β ≈ sqrt(β² + bias), so the paper's twist is wrong even for tiny moves."""
    t = perpendicular_axes_table(0.0)
    poses = random_poses(50, seed=5, box=np.array([2, 2, 2, 0.002, 0.002, 0.002]))
    ours = np.asarray(jt.rod_rotation(t, poses))
    paper = np.asarray(jt.paper_rod_rotation(t, poses))
    assert np.abs(np.abs(paper) - np.abs(ours)).max() > 2 * np.abs(ours).max()


def test_paper_form_errs_with_non_perpendicular_axes(table):
    """Reference table: fixed axes in the mounting planes, not ⟂ the tilted legs: |l|
    normalisation biases arccos, so the paper's magnitude is wrong at x = −200 mm."""
    pose = np.array([-200.0, 0, 0, 0, 0, 0])
    ours = np.asarray(jt.rod_rotation(table, pose))
    paper = np.asarray(jt.paper_rod_rotation(table, pose))
    assert np.abs(np.abs(paper) - np.abs(ours)).max() > np.deg2rad(0.5)


def _upside_down(t):
    """The same machine turned 180° about x: base above, legs pointing down."""
    Q = np.diag([1.0, -1.0, -1.0])
    h = float(t.home_height)
    return jt.replace(
        t,
        base_joints=np.asarray(t.base_joints) @ Q.T + [0, 0, 2 * h],
        platform_joints=np.asarray(t.platform_joints) @ Q.T,
        base_axes=np.asarray(t.base_axes) @ Q.T,
        platform_axes=np.asarray(t.platform_axes) @ Q.T,
    )


def test_paper_z_sign_test_fails_for_downward_legs():
    t = perpendicular_axes_table(45.0)
    flipped = _upside_down(t)
    poses = random_poses(20, seed=6, box=np.array([5, 5, 5, 0.005, 0.005, 0.005]))
    flipped_poses = poses * np.array([1, -1, -1, 1, -1, -1])  # same motion in the turned frame
    np.testing.assert_allclose(
        np.asarray(jt.leg_lengths(flipped, flipped_poses)),
        np.asarray(jt.leg_lengths(t, poses)),
        atol=1e-9,
    )
    # the model is intrinsic: same physical motion, same twist
    np.testing.assert_allclose(
        np.asarray(jt.rod_rotation(flipped, flipped_poses)),
        np.asarray(jt.rod_rotation(t, poses)),
        atol=1e-12,
    )
    # the paper's z test flips its sign
    p0 = np.asarray(jt.paper_rod_rotation(t, poses))
    p1 = np.asarray(jt.paper_rod_rotation(flipped, flipped_poses))
    ok = np.abs(p0) > 1e-5
    np.testing.assert_allclose(p1[ok], -p0[ok], rtol=1e-6)


def test_paper_form_gradient_at_home_is_infinite_model_is_finite():
    t = perpendicular_axes_table()
    g_paper = np.asarray(
        quick_jit(jax.jacfwd(lambda q: kin.paper_rod_rotation(t, q)))(jnp.zeros(6))
    )
    g_model = np.asarray(quick_jit(jax.jacfwd(lambda q: kin.rod_rotation(t, q)))(jnp.zeros(6)))
    assert not np.all(np.isfinite(g_paper))
    assert np.all(np.isfinite(g_model)) and np.abs(g_model).max() > 1e-4


def test_leg_lines_are_the_rows_of_the_rigid_jacobian(table):
    """[u_i, R a_i × u_i] = ∂L_i/∂(t, ω): central differences of the leg lengths under a small
    translation t and a small rotation ω applied in the base frame."""
    pose = jnp.asarray(random_poses(1, seed=4)[0])
    u, moment = (np.asarray(x) for x in kin.leg_lines(table, pose))
    np.testing.assert_allclose(np.linalg.norm(u, axis=1), 1.0, atol=1e-14)
    R = np.asarray(jt.rotation_matrix(pose[3:]))
    h = 1e-5

    def lengths(dt, w):
        # the platform moved by dt and turned by the small rotation w about its origin
        Rn = (np.eye(3) + np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])) @ R
        t = np.asarray(pose[:3]) + np.array([0, 0, float(table.home_height)]) + dt
        a = np.asarray(table.platform_joints) @ Rn.T
        return np.linalg.norm(t + a - np.asarray(table.base_joints), axis=1)

    for k in range(3):
        e = np.eye(3)[k] * h
        zero = np.zeros(3)
        dt = (lengths(e, zero) - lengths(-e, zero)) / (2 * h)
        dw = (lengths(zero, e) - lengths(zero, -e)) / (2 * h)
        np.testing.assert_allclose(dt, u[:, k], atol=1e-8)
        np.testing.assert_allclose(dw, moment[:, k], atol=1e-5)


def test_in_stroke_is_inclusive_and_elementwise(table):
    lo, hi = (float(v) for v in np.asarray(table.stroke))
    L = np.array([[lo, hi, lo - 1e-9, hi + 1e-9, 0.5 * (lo + hi), np.nan]])
    assert np.asarray(kin.in_stroke(table, L)).tolist() == [[True, True, False, False, True, False]]
