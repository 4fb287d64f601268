"""Sensitivities: autodiff = the paper's analytic eq. (11) = finite differences of the exact
forward map = jacfwd through the Newton solve."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import quick_jit, random_poses

import jaxtable as jt
from jaxtable._analysis.sensitivities import (
    BUDGET_WRT,
    GEOMETRY_42,
    budget_jacobians_one,
    jacobians_one,
    paper_error_jacobian,
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


@pytest.fixture(scope="module")
def fd_pose_sens(table):
    """The sensitivity to every leaf the finite-difference test perturbs, in one call."""
    pose = np.array([-150.0, 60.0, 20.0, 0.06, -0.05, 0.1])
    wrt = ("base_joints", "platform_joints", "zero_lengths", "platform_axes", "lead")
    return (pose, *pose_sensitivity(table, pose, wrt=wrt))


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
def test_sensitivity_equals_finite_differences_of_exact_forward(table, fd_pose_sens, name, index):
    """The controller commands the nominal compensated IK; the hardware leaf is off by ±h;
    exact forward kinematics (spiral inside) gives the pose. Central differences."""
    pose, J, names = fd_pose_sens
    cmd = jt.actuator_command(table, pose)
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

    Jl, Jh = quick_jit(jax.jacfwd(actual, argnums=(0, 1)))(table.lead, table.hand)
    J, _ = pose_sensitivity(table, pose, wrt=("lead", "hand"))
    np.testing.assert_allclose(np.asarray(J)[:, :6], np.asarray(Jl), rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(np.asarray(J)[:, 6:], np.asarray(Jh), rtol=1e-9, atol=1e-15)


def _perturbed_table(table, seed):
    """The reference table with joints moved by ~1 mm, axes tilted off the legs' normals and
    two left-hand screws: a geometry with no symmetry for the closed forms to lean on."""
    rng = np.random.default_rng(seed)
    axes = np.asarray(table.base_axes) + 0.2 * rng.normal(size=(6, 3))
    paxes = np.asarray(table.platform_axes) + 0.2 * rng.normal(size=(6, 3))
    return jt.replace(
        table,
        base_joints=np.asarray(table.base_joints) + rng.normal(size=(6, 3)),
        platform_joints=np.asarray(table.platform_joints) + rng.normal(size=(6, 3)),
        base_axes=axes / np.linalg.norm(axes, axis=1, keepdims=True),
        platform_axes=paxes / np.linalg.norm(paxes, axis=1, keepdims=True),
        hand=[1.0, -1.0, 1.0, 1.0, -1.0, 1.0],
    )


@pytest.mark.parametrize("perturbed", [False, True])
def test_closed_form_budget_blocks_equal_autodiff(table, perturbed):
    """The error map's closed-form blocks (pose Jacobian in (t, ω), per-leg parameter gains,
    command, spiral) against `jax.jacfwd` of the model's residual through `jacobians_one`."""
    from jaxtable._kinematics import spiral_extension
    from jaxtable._model import inverse_extension
    from jaxtable._rotation import euler_rate_matrix

    t = _perturbed_table(table, 7) if perturbed else table
    eff = budget_effects(t)
    widths = [3, 3, 1, 1, 1]  # columns per leg of each BUDGET_WRT leaf
    blocks = quick_jit(budget_jacobians_one)
    autodiff = quick_jit(lambda p: jacobians_one(t, eff, p, BUDGET_WRT))
    for pose in random_poses(4, seed=11):
        pose = jnp.asarray(pose)
        s, K, gains, spiral = (np.asarray(x) for x in blocks(t, pose))
        Jq, Jt = (np.asarray(x) for x in autodiff(pose))
        Jq_cf = K.copy()
        Jq_cf[:, 3:] = K[:, 3:] @ np.asarray(euler_rate_matrix(pose[3:]))
        np.testing.assert_allclose(Jq_cf, Jq, rtol=0, atol=1e-12 * np.abs(Jq).max())
        k = 0
        for col, m in enumerate(widths):
            block = Jt[:, k : k + 6 * m].reshape(6, 6, m)  # residual leg, parameter leg, comp
            k += 6 * m
            for i in range(6):
                assert gains[i, col] == pytest.approx(np.sum(block[i, i] ** 2), rel=1e-12)
                assert np.abs(np.delete(block[i], i, axis=0)).max() == 0.0  # legs independent
        s_ref, _ = inverse_extension(t, {"spiral": eff["spiral"]}, pose)
        np.testing.assert_allclose(s, np.asarray(s_ref), rtol=0, atol=1e-10)
        np.testing.assert_allclose(spiral, np.asarray(spiral_extension(t, pose)), atol=1e-13)
        # the spiral's share of K is far above the tolerance: a wrong twist gradient fails
        rigid = jt.replace(t, lead=0.0)
        _, K_rigid, gains_rigid, _ = (np.asarray(x) for x in budget_jacobians_one(rigid, pose))
        assert np.abs(K_rigid - K).max() > 1e-6 * np.abs(K).max()
        assert np.abs(gains_rigid[:, :2] - gains[:, :2]).max() > 1e-6


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
