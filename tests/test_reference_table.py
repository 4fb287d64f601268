"""The embedded reference table reproduces every number the paper publishes (Fig. 5/6)."""

import numpy as np
from conftest import x_line

import jaxtable as jt

XS = np.linspace(-200, 200, 401)


def test_legs_1_and_6_turn_7_36_deg_in_opposite_senses_at_x_minus_200(table):
    twist = np.rad2deg(np.asarray(jt.rod_rotation(table, x_line([-200.0]))))[0]
    assert abs(twist[0] - (-7.36)) <= 0.02  # leg 1 clockwise (seen from the platform end)
    assert abs(twist[5] - 7.36) <= 0.02  # leg 6 counter-clockwise


def test_passive_extension_0_26_mm(table):
    ext = np.asarray(jt.spiral_extension(table, x_line([-200.0])))[0]
    assert abs(abs(ext[0]) - 0.26) <= 0.005 and abs(abs(ext[5]) - 0.26) <= 0.005
    assert np.sign(ext[0]) == -np.sign(ext[5])  # same-hand screws, mirror legs


def test_legs_1_and_6_at_x_minus_200_are_the_largest(table):
    twist = np.abs(np.asarray(jt.rod_rotation(table, x_line(XS))))
    i, k = np.unravel_index(twist.argmax(), twist.shape)
    assert XS[i] == -200.0 and k in (0, 5)
    assert twist[:, [1, 2, 3, 4]].max() < twist[0, 0] - np.deg2rad(1.0)


def test_mirror_pairs_antisymmetric(table):
    twist = np.asarray(jt.rod_rotation(table, x_line(XS)))
    for i, j in ((0, 5), (1, 4), (2, 3)):
        np.testing.assert_allclose(twist[:, i], -twist[:, j], atol=1e-14)


def test_lead_is_a_half_inch_roller_screw(table):
    np.testing.assert_array_equal(np.asarray(table.signed_lead), 12.7)


def test_stated_workspace_is_reachable(table):
    """x ±200 mm (the paper's stroke) and the README's workspace: each DOF alone to its range,
    and all six together within the combined box."""
    ranges = np.array([200.0, 200.0, 100.0, np.deg2rad(15), np.deg2rad(15), np.deg2rad(20)])
    single = np.concatenate(
        [np.outer(np.linspace(-1, 1, 21), np.eye(6)[k] * ranges[k]) for k in range(6)]
    )
    assert np.asarray(jt.reachable(table, single)).all()
    box = np.array([100.0, 100.0, 50.0, np.deg2rad(7.5), np.deg2rad(7.5), np.deg2rad(10)])
    corners = np.array(np.meshgrid(*[[-1, 1]] * 6)).reshape(6, -1).T * box
    rnd = np.random.default_rng(0).uniform(-1, 1, (5000, 6)) * box
    assert np.asarray(jt.reachable(table, np.concatenate([corners, rnd]))).all()
    jt.check_reachable(table, x_line(XS))
