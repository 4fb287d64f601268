"""The effect library: each term against its defining formula (computed here independently),
the static leg forces against equilibrium, the context through inverse and forward
kinematics, and effects in table files."""

import jax.numpy as jnp
import numpy as np
import pytest
from conftest import random_poses

import jaxtable as jt
from jaxtable._context import directions
from jaxtable._errors import TableFileError

G = 9.80665


def _leg_lengths_np(table, pose):
    from scipy.spatial.transform import Rotation

    R = Rotation.from_euler("ZYX", pose[3:][::-1]).as_matrix()
    t = np.array([pose[0], pose[1], float(table.home_height) + pose[2]])
    a = np.asarray(table.platform_joints)
    b = np.asarray(table.base_joints)
    return t + a @ R.T - b, R


def test_directions_hand_case():
    cmd = np.array(
        [[0, 0, 0, 0, 0, 0], [1, -1, 0, 0, 0, 0], [1, 0, 0, 0, 0, 0], [0.5, 0, 1, 0, 0, 0]]
    )
    cmd = cmd.astype(float) + 800
    d = directions(cmd)
    np.testing.assert_array_equal(d[:, 0], [1, 1, 1, -1])  # out, stays, then in
    np.testing.assert_array_equal(d[:, 1], [1, -1, 1, 1])
    np.testing.assert_array_equal(d[:, 2], [1, 1, 1, 1])
    np.testing.assert_array_equal(d[:, 3], [1, 1, 1, 1])


def test_leg_forces_satisfy_static_equilibrium(table):
    t = jt.replace(table, platform_mass=150.0, platform_cog=[20.0, -10.0, 80.0])
    for pose in random_poses(5, seed=3):
        F = np.asarray(jt.leg_forces(t, jnp.asarray(pose), 40.0))
        l, R = _leg_lengths_np(t, pose)
        u = l / np.linalg.norm(l, axis=1, keepdims=True)
        ra = np.asarray(t.platform_joints) @ R.T
        W = np.array([0, 0, -G * 190.0])
        c = R @ np.array([20.0, -10.0, 80.0])
        # forces of the legs on the platform (tension pulls it toward the base) + weight = 0
        np.testing.assert_allclose((-F[:, None] * u).sum(0) + W, 0, atol=1e-9)
        moment = np.cross(ra, -F[:, None] * u).sum(0) + np.cross(c, W)
        np.testing.assert_allclose(moment, 0, atol=1e-6)
        assert np.all(F < 0)  # a platform standing on its legs compresses them


def test_leg_forces_symmetric_home(table):
    t = jt.replace(table, platform_mass=120.0)
    F = np.asarray(jt.leg_forces(t, jnp.zeros(6)))
    l, _ = _leg_lengths_np(t, np.zeros(6))
    uz = l[:, 2] / np.linalg.norm(l, axis=1)
    np.testing.assert_allclose(F, -120.0 * G / (6 * uz), rtol=1e-10)


def _forward_check(table, effects, ctx, extra_fn, seed=0):
    """Command poses with the rigid IK, solve FK with the effect, and check the defining
    equation |l(q)| = L0 + s + extra(q, s) with extra computed by `extra_fn` here."""
    poses = random_poses(20, seed=seed)
    cmd = np.asarray(jt.actuator_command(table, poses, compensated=False))
    q = np.asarray(jt.forward(table, cmd, effects=effects, guess=poses, context=ctx))
    s = cmd - np.asarray(table.zero_lengths)
    for i in range(len(poses)):
        l, _ = _leg_lengths_np(table, q[i])
        extra = extra_fn(i, q[i], s[i])
        np.testing.assert_allclose(
            np.linalg.norm(l, axis=1), np.asarray(table.zero_lengths) + s[i] + extra, atol=1e-8
        )
    return q, poses


def test_backlash_follows_direction(table):
    w = np.array([0.02, 0.04, 0.01, 0.03, 0.05, 0.02])
    d = np.where(np.random.default_rng(1).random((20, 6)) > 0.5, 1.0, -1.0)
    ctx = jt.Context(d, 20.0, 0.0, 0)
    q, poses = _forward_check(
        table, {"backlash": jt.Backlash(w)}, ctx, lambda i, q, s: -w / 2 * d[i]
    )
    assert 1e-4 < np.abs(q - poses)[:, :3].max() < 0.2


def test_thermal_grows_with_temperature(table):
    alpha = 11.5e-6 * np.array([1, 1.1, 0.9, 1, 1.2, 0.8])
    T = np.linspace(15, 35, 20)
    ctx = jt.Context(1.0, T, 0.0, 0)
    L0 = np.asarray(table.zero_lengths)
    _forward_check(
        table, {"thermal": jt.Thermal(alpha)}, ctx, lambda i, q, s: alpha * (T[i] - 20) * L0
    )


def test_periodic_lead_and_lead_scale_in_the_inverse(table):
    a = np.array([0.005, -0.003, 0.004, 0.0, 0.002, -0.005])
    b = np.array([0.001, 0.004, -0.002, 0.005, 0.0, 0.003])
    eff = {"periodic_lead": jt.PeriodicLead(a, b), "lead_scale": jt.LeadScale(8e-5)}
    poses = random_poses(30, seed=4)
    cmd = np.asarray(jt.actuator_command(table, poses, effects=eff))
    s = cmd - np.asarray(table.zero_lengths)
    p = 12.7
    L = np.asarray(jt.leg_lengths(table, poses))
    rhs = (
        np.asarray(table.zero_lengths)
        + s
        + 8e-5 * s
        + a * np.sin(2 * np.pi * s / p)
        + b * np.cos(2 * np.pi * s / p)
    )
    np.testing.assert_allclose(L, rhs, atol=1e-10)


def test_compliance_shortens_legs_by_force_over_stiffness(table):
    t = jt.replace(table, platform_mass=150.0, platform_cog=[0.0, 0.0, 60.0])
    k = np.array([2e4, 3e4, 2.5e4, 2e4, 1.5e4, 2e4])
    payload = np.linspace(0, 100, 20)
    ctx = jt.Context(1.0, 20.0, payload, 0)

    def extra(i, q, s):
        return np.asarray(jt.leg_forces(t, jnp.asarray(q), payload[i])) / k

    q, poses = _forward_check(t, {"compliance": jt.Compliance.from_k(k)}, ctx, extra)
    # the platform sags: lower than commanded, more with more payload
    sag = (q - poses)[:, 2]
    assert np.all(sag < 0) and sag[-1] < sag[0]


def test_rehoming_shifts_later_sessions(table):
    off = np.array([[0.03, -0.02, 0.01, 0.0, 0.05, -0.04], [0.01, 0.01, 0.01, 0.01, 0.01, 0.01]])
    sess = np.repeat([0, 1, 2], [6, 7, 7])
    ctx = jt.Context(1.0, 20.0, 0.0, sess)
    rows = np.concatenate([np.zeros((1, 6)), off])
    _forward_check(table, {"rehoming": jt.Rehoming(off)}, ctx, lambda i, q, s: rows[sess[i]])


def test_effects_are_zero_at_null(table):
    pose = jnp.asarray(random_poses(1, seed=5)[0])
    t = jt.replace(table, platform_mass=100.0)
    ctx = jt.Context(-1.0, 31.0, 50.0, 1)
    for name, cls in jt.EFFECTS.items():
        e = cls.null(n_sessions=2)
        np.testing.assert_array_equal(
            np.asarray(e(t, pose, jnp.full(6, 37.0), ctx)), 0.0, err_msg=name
        )


def test_effects_round_trip_through_table_file(table, tmp_path):
    eff = {
        "spiral": jt.Spiral([12.7, -12.7, 12.7, 12.7, -10.0, 12.7]),
        "backlash": jt.Backlash(0.02),
        "compliance": jt.Compliance.from_k(np.array([2e4, 2.1e4, 2.2e4, 2.3e4, 2.4e4, 2.5e4])),
        "rehoming": jt.Rehoming([[0.01, 0.02, 0.03, 0.04, 0.05, 0.06]]),
        "thermal": jt.Thermal(1.1e-5),
    }
    path = tmp_path / "t.toml"
    jt.save_table(table, path, effects=eff)
    text = path.read_text()
    assert "[effects.compliance]" in text and "k = [20000.0" in text
    t2, e2 = jt.load_model(path)
    assert set(e2) == set(eff)
    for name in eff:
        for f in type(eff[name]).fields:
            np.testing.assert_array_equal(
                np.asarray(getattr(e2[name], f)), np.asarray(getattr(eff[name], f))
            )
    np.testing.assert_array_equal(np.asarray(t2.base_joints), np.asarray(table.base_joints))
    assert jt.load_model(jt.__path__[0] + "/data/reference_table.toml")[1] is None


def test_bad_effect_tables_are_refused(table, tmp_path):
    path = tmp_path / "t.toml"
    jt.save_table(table, path)
    base = path.read_text()
    path.write_text(base + "\n[effects.friction]\nmu = 0.1\n")
    with pytest.raises(TableFileError, match="unknown effect \\[effects.friction\\]"):
        jt.load_model(path)
    path.write_text(base + "\n[effects.backlash]\nwidth = 0.1\n")
    with pytest.raises(TableFileError, match="unknown key 'width'.*allowed: w"):
        jt.load_table(path)
