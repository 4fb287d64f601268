"""Discovery beyond the library: the dictionary terms as a model effect, and terms planted in
simulated tracker data (the reference table with random geometric errors: joints σ 10 µm,
L0 σ 50 µm; 6-D tracker noise) at realistic magnitudes: each must be found as that term, on
its legs, with its coefficient within 3σ, and no library effect named in its place."""

import dataclasses
import tomllib

import jax.numpy as jnp
import numpy as np
import pytest

import jaxtable as jt
from jaxtable._calibration.instruments import tracker6
from jaxtable._calibration.simulate import perturb_table, plan_random, simulate
from jaxtable._context import Context
from jaxtable._effects import Discovered
from jaxtable._io import effects_from_dict, effects_to_toml

N = 150


def _quiet(_):
    pass


# --- the model term ------------------------------------------------------------------------


def test_discovered_terms_by_hand():
    cross = np.zeros((6, 6))
    cross[1, 4] = 2e-3
    d = Discovered(
        s2=[0, 0, 3e-6, 0, 0, 0],
        s3_all=1e-9,
        cross=cross,
        cross_all=[0, 0, 0, 0, 0, 1e-4],
        ds=[0, 5e-5, 0, 0, 0, 0],
        Ts_all=1e-5,
        t=[0.02, 0, 0, 0, 0, 0],
        session_s=[[0, 0, 0, 1e-4, 0, 0]],
        session_s_all=[2e-5],
    )
    s = np.array([10.0, -20.0, 30.0, 40.0, -50.0, 60.0])
    ctx = Context(direction=[1, -1, 1, -1, 1, -1], temperature=26.0, session=1, time=0.25)
    got = np.asarray(d(jt.reference_table(), jnp.zeros(6), jnp.asarray(s), ctx))
    want = np.zeros(6)
    want[2] += 3e-6 * 30.0**2
    want += 1e-9 * s**3
    want[1] += 2e-3 * -50.0  # leg 2 from leg 5
    want[:5] += 1e-4 * 60.0  # leg 6 onto every other leg
    want[1] += 5e-5 * -1 * -20.0
    want += 1e-5 * 6.0 * s
    want[0] += 0.02 * 0.25
    want[3] += 1e-4 * 40.0
    want += 2e-5 * s
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)
    # first session: no session term
    ctx0 = dataclasses.replace(ctx, session=jnp.asarray(0))
    got0 = np.asarray(d(jt.reference_table(), jnp.zeros(6), jnp.asarray(s), ctx0))
    np.testing.assert_allclose(got0, want - 2e-5 * s - np.eye(6)[3] * 1e-4 * 40.0, atol=1e-15)
    # file round trip
    back = effects_from_dict(tomllib.loads(effects_to_toml({"discovered": d})))["discovered"]
    np.testing.assert_allclose(back(jt.reference_table(), jnp.zeros(6), jnp.asarray(s), ctx), got)


def test_forward_and_inverse_with_crosstalk_round_trip():
    table = jt.reference_table()
    cross = np.zeros((6, 6))
    cross[1, 4], cross[3, 0] = 2e-3, -1.5e-3
    eff = {"spiral": jt.Spiral.from_table(table), "discovered": Discovered(cross=cross)}
    poses = np.random.default_rng(0).uniform(-1, 1, (50, 6)) * [80, 80, 40, 0.1, 0.1, 0.15]
    lengths = jt.actuator_command(table, poses, effects=eff)
    back = jt.forward(table, lengths, effects=eff)
    np.testing.assert_allclose(np.asarray(back), poses, atol=1e-9)
    # the crosstalk is really there: the rigid inverse differs by c·s_j
    plain = jt.actuator_command(table, poses, effects={"spiral": eff["spiral"]})
    assert np.max(np.abs(np.asarray(plain) - np.asarray(lengths))) > 0.05


# --- screening: false discoveries on noise-only data ----------------------------------------


def _plant(eff, seed, sessions=1, **kw):
    nominal = jt.replace(jt.reference_table(), platform_mass=150.0, platform_cog=[0.0, 0.0, 60.0])
    true = perturb_table(nominal, seed, joint_sigma=0.010, zero_sigma=0.050)
    rng = np.random.default_rng(1000 + seed)
    kw.setdefault("temperature", 20 + 10 * np.arange(N) / N + rng.normal(0, 0.2, N))
    kw.setdefault("payload", rng.choice([0.0, 50.0, 100.0], N))
    if sessions > 1:
        kw["session"] = np.array([f"s{1 + k * sessions // N}" for k in range(N)])
        kw["frame"] = [[0, 0, 0, 0, 0, 0], [20.0, -10.0, 5.0, 0.01, 0.0, -0.02]][:sessions]
    data = simulate(
        nominal,
        true,
        plan_random(N, seed),
        tracker6(),
        effects=eff,
        compensated=False,
        seed=seed,
        **kw,
    )
    return nominal, data


# The dictionary's false-discovery rate on noise-only data is counted with the structure
# test's false alarms, on the same fits: tests/test_structure.py.


# --- planted terms ------------------------------------------------------------------------


def _check_found(diag, term, legs, truth):
    assert diag.selected == [], diag.selected  # no library name forced on it
    assert [f.candidate.term for f in diag.discovered][:1] == [term], diag.as_json()["discovered"]
    f = diag.discovered[0]
    assert list(f.candidate.legs) == list(legs), f.candidate.label
    z = (f.coefficient - np.asarray(truth)) / f.std
    assert np.all(np.abs(z) < 3.0), (f.coefficient, f.std, truth)
    assert f.heldout_gain > 0 and f.words
    assert not diag.unexplained


def _cross(i, j, c):
    m = np.zeros((6, 6))
    m[i - 1, j - 1] = c
    return m


PLANTED = {
    # name: (effect, term, legs, true coefficient(s), simulate kwargs)
    "s^2 leg 3": (Discovered(s2=[0, 0, 3e-6, 0, 0, 0]), "s^2", (3,), [3e-6], {}),
    "T*s shared": (Discovered(Ts_all=1.5e-5), "T*s", (1, 2, 3, 4, 5, 6), [1.5e-5], {}),
    "s[5] on leg 2": (Discovered(cross=_cross(2, 5, 2e-3)), "s[5]", (2,), [2e-3], {}),
}
PLANTED_SLOW = {
    # the lab's temperature cycles (air conditioning) rather than following the run: a
    # drift is then not a thermal effect (see the ambiguity test for when it is)
    "t leg 1": (
        Discovered(t=[0.02, 0, 0, 0, 0, 0]),
        "t",
        (1,),
        [0.02],
        {"temperature": 21 + 2 * np.sin(2 * np.pi * 3 * np.arange(N) / N)},
    ),
    "d*s shared": (Discovered(ds_all=1e-4), "d*s", (1, 2, 3, 4, 5, 6), [1e-4], {}),
    "s^3 leg 4": (Discovered(s3=[0, 0, 0, 4e-8, 0, 0]), "s^3", (4,), [4e-8], {}),
    "s^2 per leg": (
        Discovered(s2=[3e-6, -2e-6, 2.5e-6, -3e-6, 2e-6, -2.5e-6]),
        "s^2",
        (1, 2, 3, 4, 5, 6),
        [3e-6, -2e-6, 2.5e-6, -3e-6, 2e-6, -2.5e-6],
        {},
    ),
    "session*s shared": (
        Discovered(session_s=np.zeros((1, 6)), session_s_all=[2e-4]),
        "session*s",
        (1, 2, 3, 4, 5, 6),
        [2e-4],
        {"sessions": 2},
    ),
}


def _run_planted(name, table, seed=5):
    eff, term, legs, truth, kw = table[name]
    nominal, data = _plant({"discovered": eff}, seed, **kw)
    diag = jt.diagnose(nominal, data, log=_quiet, compensated=False)
    _check_found(diag, term, legs, truth)
    return diag


@pytest.mark.parametrize("name", list(PLANTED))
def test_planted_term_is_found_named_and_recovered(name):
    _run_planted(name, PLANTED)


@pytest.mark.slow
@pytest.mark.parametrize("name", list(PLANTED_SLOW))
def test_planted_term_every_family(name):
    _run_planted(name, PLANTED_SLOW)


def test_library_effect_with_a_term_and_the_model_file(tmp_path):
    """Spiral (library) plus an s^2 error on leg 3: the spiral is named as the library
    effect, the term as a term; the final model, saved and read back, predicts the data."""
    nominal = jt.replace(jt.reference_table(), platform_mass=150.0, platform_cog=[0, 0, 60.0])
    eff = {
        "spiral": jt.Spiral.from_table(nominal),
        "discovered": Discovered(s2=[0, 0, 3e-6, 0, 0, 0]),
    }
    nominal, data = _plant(eff, 8)
    diag = jt.diagnose(nominal, data, log=_quiet, compensated=False)
    assert diag.selected == ["spiral"], diag.selected
    assert [(f.candidate.term, f.candidate.legs) for f in diag.discovered] == [("s^2", (3,))]
    doc = diag.as_json()
    assert {"discovered", "absorbed", "ambiguous"} <= set(doc)
    assert doc["discovered"][0]["term"] == "s^2" and doc["discovered"][0]["legs"] == [3]
    path = tmp_path / "model.toml"
    jt.save_fitted_model(diag.fitted_model(), path)
    model = jt.load_fitted_model(path)
    assert "discovered" in model.effects
    assert np.asarray(model.effects["discovered"].s2)[2] == pytest.approx(
        diag.discovered[0].coefficient[0]
    )
    v = jt.validate(model, data)
    assert v.rms["x"] < 0.02  # at the tracker's noise (10 µm), not the 80 µm the term makes


def test_absorbed_term_is_reported():
    """Temperature rising exactly linearly with time and a thermal effect in the model: a
    drift over the run (`t`) is what thermal already does, so it is absorbed, not tested."""
    nominal, data = _plant({}, 9, temperature=20 + 10 * np.arange(N) / (N - 1))
    diag = jt.diagnose(nominal, data, base=("thermal",), log=_quiet, compensated=False)
    assert "t" in diag.absorbed, diag.absorbed
    assert diag.discovered == []


def test_ambiguous_terms_are_reported_with_a_plan(tmp_path):
    """Temperature that steps with the session (20 °C in the first, 30 °C in the second): a
    scale that grows with temperature and a scale that changes between sessions are the same
    function of these data, so the finding is reported ambiguous, with a pose plan that says
    poses alone cannot separate them."""
    temperature = np.where(np.arange(N) < N // 2, 20.0, 30.0)
    nominal, data = _plant(
        {"discovered": Discovered(Ts_all=1.5e-5)}, 12, sessions=2, temperature=temperature
    )
    diag = jt.diagnose(nominal, data, log=_quiet, compensated=False)
    assert diag.discovered, diag.as_json()["steps"][0]["dictionary"]
    group = {c.term for c in diag.ambiguous[0]}
    assert {"T*s", "session*s"} <= group, group
    paths = jt.reports.write_diagnosis_report(diag, tmp_path, "test data")
    plans = [p for p in paths if p.name.startswith("plan_")]
    assert len(plans) == 1
    rows = plans[0].read_text().splitlines()
    assert rows[0].startswith("cmd_x,cmd_y,cmd_z,cmd_roll,cmd_pitch,cmd_yaw") and len(rows) == 21
    assert "Ambiguous" in (tmp_path / "report.md").read_text()
    doc = diag.as_json()
    assert {"T*s", "session*s"} <= set(doc["ambiguous"][0])
    assert doc["ambiguous_detail"][0]["plan"] == plans[0].name
    # the two differ only in the conditions: a plan continuing the last session at its
    # temperature cannot separate them, and the report says so
    assert doc["ambiguous_detail"][0]["separates"] is False
    assert doc["ambiguous_detail"][0]["correlation"][1] > 0.95
    assert "poses alone cannot" in (tmp_path / "report.md").read_text()


def test_library_effect_and_term_the_data_cannot_tell_apart():
    """A drift over the run on leg 1 while the temperature rises with time: thermal growth
    (library) does the same to these data, so the library effect is named and the pair is
    reported ambiguous."""
    eff, *_ = PLANTED_SLOW["t leg 1"]
    nominal, data = _plant({"discovered": eff}, 5)  # temperature rising with time
    diag = jt.diagnose(nominal, data, log=_quiet, compensated=False)
    assert diag.selected == ["thermal"] and diag.discovered == [], diag.selected
    doc = diag.as_json()
    assert doc["ambiguous"] == [["thermal", "t"]], doc["ambiguous"]
    assert doc["ambiguous_detail"][0]["candidates"] == ["thermal (library effect)", "t on leg 1"]


def test_discrimination_plan_beats_as_many_random_poses():
    """s² and s³ on leg 3, on a run whose stops all extend the legs (z from 30 to 60 mm): on
    a one-sided range the two curves are nearly proportional, so their coefficients are
    confounded. The Ds-optimal plan (20 poses from 600 candidates) must separate them better
    than 20 random poses from the same box (a plan drawn from exactly 20 candidates), in both
    of its measures (the correlation of the two coefficients and the Δχ² by which s³ would
    fit worse), and name the conditions it assumes."""
    from jaxtable._calibration.fit import fit
    from jaxtable._discovery.diagnose import discovery_setup
    from jaxtable._discovery.dictionary import candidates, discrimination_plan
    from jaxtable._params import GEOMETRY

    nominal = jt.reference_table()
    rng = np.random.default_rng(4)
    lo, hi = np.array([-20, -20, 30, -0.02, -0.02, -0.02]), np.array([20, 20, 60, 0.02, 0.02, 0.02])
    poses = lo + rng.uniform(size=(60, 6)) * (hi - lo)
    true = perturb_table(nominal, 4, joint_sigma=0.010, zero_sigma=0.050)
    eff = {"discovered": Discovered(s2=[0, 0, 3e-6, 0, 0, 0])}
    data = simulate(nominal, true, poses, tracker6(), effects=eff, compensated=False, seed=4)
    st = discovery_setup(nominal, data, compensated=False)
    by_label = {c.label: c for c in candidates(st, data)}
    group = [by_label["s^2 on leg 3"], by_label["s^3 on leg 3"]]
    mask = st.free_mask(GEOMETRY)
    mask[st.names.index("discovered.s2[3]")] = 1.0
    cal = fit(st, mask)
    plan = discrimination_plan(cal, st, data, group, 20, candidates=600)
    rand = discrimination_plan(cal, st, data, group, 20, candidates=20, seed=1)
    assert plan.poses.shape == (20, 6)
    assert plan.correlation_before == pytest.approx(rand.correlation_before)
    assert plan.correlation_before > 0.9  # confounded by these data
    assert plan.correlation_after < rand.correlation_after < plan.correlation_before
    assert plan.separation_after > rand.separation_after > plan.separation_before
    assert plan.context == {"session": "1", "temperature": 20.0, "payload": 0.0}
    assert f"{plan.correlation_after:.2f}" in plan.words()
