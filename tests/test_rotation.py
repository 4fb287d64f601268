import jax.numpy as jnp
import numpy as np
import pytest

import jaxtable as jt


def Rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def Ry(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def Rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


@pytest.mark.parametrize("seed", range(5))
def test_rotation_is_zyx_composition(seed):
    phi, theta, psi = np.random.default_rng(seed).uniform(-2, 2, 3)
    R = np.asarray(jt.rotation_matrix(np.array([phi, theta, psi])))
    np.testing.assert_allclose(R, Rz(psi) @ Ry(theta) @ Rx(phi), atol=1e-15)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-15)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-14)


def test_paper_eq2_typos_are_exactly_three_elements():
    """The printed eq. (2) differs from Rz Ry Rx at (1,3), (2,2), (2,3) (1-based) only."""
    rng = np.random.default_rng(1)
    for _ in range(20):
        angles = rng.uniform(-1.2, 1.2, 3)
        good = np.asarray(jt.rotation_matrix(angles))
        printed = np.asarray(jt.paper_rotation_matrix(angles))
        differs = ~np.isclose(good, printed, atol=1e-12)
        expected = np.zeros((3, 3), bool)
        expected[0, 2] = expected[1, 1] = expected[1, 2] = True
        np.testing.assert_array_equal(differs, expected)
    # the printed matrix is not a rotation
    P = np.asarray(jt.paper_rotation_matrix(np.array([0.3, 0.4, 0.5])))
    assert np.abs(P @ P.T - np.eye(3)).max() > 1e-2


def test_euler_rate_matrix_matches_finite_difference():
    angles = np.array([0.2, -0.4, 0.7])
    rates = np.array([0.3, -0.1, 0.25])
    h = 1e-6
    R = np.asarray(jt.rotation_matrix(angles))
    Rdot = (
        np.asarray(jt.rotation_matrix(angles + h * rates))
        - np.asarray(jt.rotation_matrix(angles - h * rates))
    ) / (2 * h)
    W = Rdot @ R.T  # skew(ω)
    omega = np.array([W[2, 1], W[0, 2], W[1, 0]])
    E = np.asarray(jt.euler_rate_matrix(angles))
    np.testing.assert_allclose(E @ rates, omega, atol=1e-9)
    np.testing.assert_allclose(np.asarray(jt.euler_rate_matrix(np.zeros(3))), np.eye(3))


@pytest.mark.parametrize("seed", range(5))
def test_euler_from_matrix_inverts_rotation_matrix(seed):
    angles = np.random.default_rng(10 + seed).uniform([-3, -1.5, -3], [3, 1.5, 3])
    back = np.asarray(jt.euler_from_matrix(Rz(angles[2]) @ Ry(angles[1]) @ Rx(angles[0])))
    np.testing.assert_allclose(back, angles, atol=1e-12)


def _exp(w):
    """Rodrigues' formula, written independently of jaxtable."""
    theta = np.linalg.norm(w)
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]) / theta
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K


@pytest.mark.parametrize("angle", [1e-9, 1e-4, 0.3, 2.0, 3.1])
def test_rotation_log_inverts_rodrigues(angle):
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    w = angle * axis
    np.testing.assert_allclose(np.asarray(jt.rotation_log(_exp(w))), w, rtol=1e-9, atol=1e-15)


def test_pose_error_hand_computed():
    # actual = commanded turned by 0.01 rad about base z, with the attitude at (0, 0, yaw):
    # the rotation vector is (0, 0, 0.01), and the translation error is the difference
    cmd = np.array([10.0, -5.0, 2.0, 0.0, 0.0, 0.3])
    act = np.array([10.2, -5.0, 1.9, 0.0, 0.0, 0.31])
    np.testing.assert_allclose(
        np.asarray(jt.pose_error(act, cmd)), [0.2, 0.0, -0.1, 0.0, 0.0, 0.01], atol=1e-13
    )
    # away from zero attitude the rotation vector is not the Euler difference: a roll
    # increment at pitch 60° is a rotation about the platform's x axis, R(θ)·e_x in the base
    cmd = np.array([0.0, 0.0, 0.0, 0.0, np.pi / 3, 0.0])
    act = cmd + np.array([0, 0, 0, 1e-3, 0, 0])
    err = np.asarray(jt.pose_error(act, cmd))
    np.testing.assert_allclose(err[3:], 1e-3 * Ry(np.pi / 3)[:, 0], atol=1e-9)
    # batched and broadcast
    many = np.asarray(jt.pose_error(np.tile(act, (4, 3, 1)), cmd))
    assert many.shape == (4, 3, 6)
    np.testing.assert_allclose(many[2, 1], err, atol=1e-15)


def test_wrapped_reading_difference_in_numpy_equals_the_jax_form():
    """Angle columns wrapped into [−π, π), positions untouched; a host array in gives a
    host array out with the same numbers as the jax form."""
    from jaxtable._rotation import wrap_reading_difference

    d = np.array([[1.0, -2.0, 3.0, 0.1, 3.5, -7.0], [0.0, 0.0, 0.0, -np.pi, np.pi, 2 * np.pi]])
    want = d.copy()
    want[:, 3:] = [[0.1, 3.5 - 2 * np.pi, -7.0 + 2 * np.pi], [-np.pi, -np.pi, 0.0]]
    host = wrap_reading_difference(d)
    assert isinstance(host, np.ndarray)
    np.testing.assert_allclose(host, want, rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(wrap_reading_difference(jnp.asarray(d))), host, atol=0)


def test_euler_angles_of_a_host_matrix_in_numpy():
    """`euler_from_matrix` of a numpy matrix is numpy, the inverse of `rotation_matrix`, and
    equals the jax form."""
    from jaxtable._rotation import euler_from_matrix, rotation_matrix

    a = np.array([0.3, -1.2, 2.9])
    R = np.asarray(rotation_matrix(jnp.asarray(a)))
    host = euler_from_matrix(R)
    assert isinstance(host, np.ndarray)
    np.testing.assert_allclose(host, a, rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.asarray(euler_from_matrix(jnp.asarray(R))), host, atol=1e-15)


def test_other_conventions_and_the_best_rotation_against_scipy():
    """`euler_matrices` in every order and sense equals scipy's intrinsic rotations of the
    same angles; `best_rotation` recovers a rotation from noisy rotated vectors and keeps
    det = +1 where the vectors are reflected."""
    from scipy.spatial.transform import Rotation

    from jaxtable._rotation import best_rotation, euler_matrices

    rng = np.random.default_rng(3)
    a = rng.uniform(-1.2, 1.2, (20, 3))  # roll, pitch, yaw
    np.testing.assert_allclose(
        euler_matrices(a), [Rz(y) @ Ry(p) @ Rx(r) for r, p, y in a], atol=1e-15
    )
    for order in ("zyx", "zxy", "yxz", "yzx", "xzy", "xyz"):
        signs = rng.choice([-1, 1], 3)
        angles = [a[:, "xyz".index(k)] * signs["xyz".index(k)] for k in order]
        want = Rotation.from_euler(order.upper(), np.stack(angles, 1)).as_matrix()
        np.testing.assert_allclose(euler_matrices(a, order, signs), want, atol=1e-15)
    R = Rotation.random(random_state=4).as_matrix()
    P = rng.normal(size=(30, 3))
    Q = P @ R.T + 1e-6 * rng.normal(size=(30, 3))
    found, S = best_rotation(P, Q)
    assert np.abs(found - R).max() < 1e-6 and S[2] > 0
    mirrored, _ = best_rotation(P, Q * [1, 1, -1])
    assert np.isclose(np.linalg.det(mirrored), 1.0)
