"""Sensitivities: autodiff = the paper's analytic eq. (11) = finite differences of the exact
forward map = jacfwd through the Newton solve."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import random_poses

import jaxtable as jt
from jaxtable._analysis.sensitivities import (
    GEOMETRY_42,
    jacobians_one,
    paper_error_jacobian,
    per_leg_jacobians_one,
    pose_sensitivity,
)
from jaxtable._analysis.tolerances import budget_effects


@pytest.fixture(scope="module")
def poses():
    p = random_poses(20, seed=21)
    p[0] = 0.0
    p[1] = [-200, 0, 0, 0, 0, 0]
    return p


def test_autodiff_equals_paper_eq11(table, poses):
    J, names = pose_sensitivity(table, poses, effects={}, rotation_vector=True)
    Jp = np.asarray(paper_error_jacobian(table, poses))
    J = np.asarray(J)
    assert J.shape == (20, 6, 42) and len(names) == 42
    assert names[0] == "zero_lengths[1]" and names[6] == "platform_joints[1].x"
    assert names[24] == "base_joints[1].x"
    rel = np.abs(J - Jp).max(axis=(1, 2)) / np.abs(Jp).max(axis=(1, 2))
    assert rel.max() < 1e-9


def test_euler_increments_are_rotation_vector_through_rate_matrix(table, poses):
    Je, _ = pose_sensitivity(table, poses, effects={})
    Jp = np.asarray(paper_error_jacobian(table, poses))
    for k in range(len(poses)):
        E = np.asarray(jt.euler_rate_matrix(poses[k, 3:]))
        np.testing.assert_allclose(
            np.asarray(Je)[k, 3:],
            np.linalg.solve(E, Jp[k, 3:]),
            rtol=0,
            atol=1e-12 * np.abs(Jp[k]).max(),
        )
    # at zero attitude the two agree (the paper's assumption), elsewhere they differ
    assert np.abs(np.asarray(Je)[0, 3:] - Jp[0, 3:]).max() < 1e-15
    assert np.abs(np.asarray(Je)[5, 3:] - Jp[5, 3:]).max() > 1e-4 * np.abs(Jp[5, 3:]).max()


def _hardware(table, name, index, h):
    leaf = np.array(getattr(table, name))
    leaf[index] += h
    return jt.replace(table, **{name: leaf})


@pytest.mark.parametrize(
    "name, index",
    [
        ("base_joints", (2, 1)),
        ("platform_joints", (4, 0)),
        ("zero_lengths", (5,)),
        ("platform_axes", (0, 2)),
        ("lead", (3,)),
    ],
)
def test_sensitivity_equals_finite_differences_of_exact_forward(table, name, index):
    """The controller commands the nominal compensated IK; the hardware leaf is off by ±h;
    exact forward kinematics (spiral inside) gives the pose. Central differences."""
    pose = np.array([-150.0, 60.0, 20.0, 0.06, -0.05, 0.1])
    cmd = jt.actuator_command(table, pose)
    J, names = pose_sensitivity(table, pose, wrt=(name,))
    col = names.index(
        f"{name}[{index[0] + 1}]" + ("" if len(index) == 1 else "." + "xyz"[index[1]])
    )
    h = 1e-3 if name != "platform_axes" else 1e-5

    def actual(dh):
        return np.asarray(jt.forward(_hardware(table, name, index, dh), cmd, nominal=table))

    fd = (actual(h) - actual(-h)) / (2 * h)
    np.testing.assert_allclose(
        np.asarray(J)[:, col], fd, rtol=1e-5, atol=1e-9 * np.abs(fd).max() + 1e-13
    )
    assert np.abs(fd).max() > 1e-6


def test_sensitivity_equals_jacfwd_through_newton_solve(table):
    pose = np.array([120.0, -40.0, -30.0, -0.05, 0.07, -0.12])
    cmd = jt.actuator_command(table, pose)

    def actual(lead, hand):
        return jt.forward(jt.replace(table, lead=lead, hand=hand), cmd)

    Jl, Jh = jax.jacfwd(actual, argnums=(0, 1))(table.lead, table.hand)
    J, _ = pose_sensitivity(table, pose, wrt=("lead", "hand"))
    np.testing.assert_allclose(np.asarray(J)[:, :6], np.asarray(Jl), rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(np.asarray(J)[:, 6:], np.asarray(Jh), rtol=1e-9, atol=1e-15)


def test_per_leg_compressed_jacobian_equals_general(table):
    pose = jnp.asarray(random_poses(1, seed=4)[0])
    wrt = ("base_joints", "platform_joints", "zero_lengths", "lead_scale.eps", "spiral.lead")
    eff = budget_effects(table)
    Jq, Jt = jacobians_one(table, eff, pose, wrt)
    Jq2, per_leg = per_leg_jacobians_one(table, eff, pose, wrt)
    np.testing.assert_allclose(np.asarray(Jq2), np.asarray(Jq), rtol=1e-14, atol=1e-15)
    k = 0
    for d in per_leg:
        m = d.shape[1]
        block = np.asarray(Jt)[:, k : k + 6 * m].reshape(6, 6, m)
        for i in range(6):
            np.testing.assert_allclose(block[i, i], np.asarray(d)[i], rtol=1e-13, atol=1e-16)
            off = np.delete(block[i], i, axis=0)
            assert np.abs(off).max() == 0.0  # leg i's residual ignores other legs' params
        k += 6 * m


def test_effect_parameters_and_unknown_names(table):
    eff = {"spiral": jt.Spiral.from_table(table)}
    J, names = pose_sensitivity(
        table, np.array([-200.0, 0, 0, 0, 0, 0]), wrt=("spiral.lead",), effects=eff
    )
    assert names == [f"spiral.lead[{i}]" for i in range(1, 7)]
    assert np.abs(np.asarray(J)).max() > 1e-3
    with pytest.raises(ValueError, match="unknown parameter 'colour'"):
        pose_sensitivity(table, np.zeros(6), wrt=("colour",))
    with pytest.raises(ValueError, match="no effect 'backlash'"):
        pose_sensitivity(table, np.zeros(6), wrt=("backlash.width",))
    assert GEOMETRY_42 == ("zero_lengths", "platform_joints", "base_joints")
