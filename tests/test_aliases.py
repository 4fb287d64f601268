"""A lead error common to all six screws and an instrument whose positions read (1 + ε) times
the true ones give the same readings: shown exactly by a table scaled by hand, and named
when a fit or a diagnosis finds lead_scale on every leg (equal legs: the instrument cannot
be told from the screws; unequal legs: the screws', their mean still either)."""

import dataclasses
import json

import numpy as np

import jaxtable as jt
from jaxtable._calibration.aliases import instrument_scale
from jaxtable.cli import main

EPS = 2e-4  # the instrument's length scale, 200 ppm
FRAME = (300.0, -200.0, 800.0, 0.1, 0.2, 0.3)  # the tracker's frame (mm, rad)


def _scaled_instrument(table, true, poses, eps=EPS, seed=7):
    """A 6-D tracker whose positions read (1 + eps) times the true ones, about its origin."""
    d = jt.simulate(table, true, poses, jt.tracker6(), frame=FRAME, seed=seed)
    m = d.measured.copy()
    m[:, :3] *= 1 + eps
    return dataclasses.replace(d, measured=m, sigma=None)


def test_a_common_lead_error_reads_as_the_instrument_s_length_scale(table):
    """The table scaled by hand by (1 + ε) (joints, home lengths and height, spiral lead) with
    a lead error ε on every screw, read by an exact tracker whose frame is scaled alike, gives the
    readings of the table read by a tracker (1 + ε) long, to 1e-9 mm and 1e-12 rad: every
    leg is (1 + ε) times as long, the angles do not change."""
    true = jt.perturb_table(table, 7)
    poses = jt.plan_random(40, 8)
    exact = jt.tracker6(1e-15, 1e-18)
    long = jt.simulate(table, true, poses, exact, frame=FRAME)
    f = 1 + EPS
    big = jt.replace(true, base_joints=true.base_joints * f,
                     platform_joints=true.platform_joints * f,
                     zero_lengths=true.zero_lengths * f, home_height=true.home_height * f,
                     lead=true.lead * f)  # fmt: skip
    frame = np.r_[np.asarray(FRAME[:3]) * f, FRAME[3:]]
    effects = {"spiral": jt.Spiral.from_table(big), "lead_scale": jt.LeadScale(EPS)}
    screws = jt.simulate(table, big, poses, exact, frame=frame, effects=effects)
    np.testing.assert_allclose(screws.measured[:, :3], long.measured[:, :3] * f, rtol=0, atol=1e-9)
    np.testing.assert_allclose(screws.measured[:, 3:], long.measured[:, 3:], rtol=0, atol=1e-12)
    assert np.abs(screws.measured[:, :3] - long.measured[:, :3]).max() > 0.01  # the scale shows


def _lead_scale_fit(table, data):
    effects = {"spiral": jt.Spiral.from_table(table), "lead_scale": jt.LeadScale(0.0)}
    return jt.calibrate(table, data, jt.GEOMETRY + ("lead_scale.eps",), effects=effects)


def test_lead_scale_on_every_leg_is_named_with_the_instrument_scale_it_cannot_be_told_from(
    table, tmp_path, capsys
):
    """A tracker 200 ppm long (150 stops): lead_scale fitted on every leg gives six equal ε
    (the test of equal legs does not reject them) whose common value is the tracker's scale
    within 3 σ, and the words say the data cannot tell the screws from the instrument.
    Screws of six different lead errors (−200 to +300 ppm, a true instrument): equal legs
    rejected, and the words say the differences are the screws'. `diagnose` names it in its
    JSON (`instrument_scale`) and report."""
    true = jt.perturb_table(table, 5)
    poses = jt.plan_random(150, 6)
    d = _scaled_instrument(table, true, poses)
    cal = _lead_scale_fit(table, d)
    alias = instrument_scale(cal, np.isfinite(d.measured))
    assert alias.agree and alias.equal_legs_p > 0.01, alias
    assert abs(alias.eps - EPS) < 3 * alias.std and alias.std < 2e-5, alias
    assert "cannot tell the screws' leads from the instrument's scale" in alias.words()
    eps = np.array([3, -2, 1, 0, 2.5, -1.5]) * 1e-4
    effects = {"spiral": jt.Spiral.from_table(table), "lead_scale": jt.LeadScale(eps)}
    own = jt.simulate(table, true, poses, jt.tracker6(), frame=FRAME, effects=effects, seed=7)
    alias = instrument_scale(_lead_scale_fit(table, own), np.isfinite(own.measured))
    assert not alias.agree and alias.equal_legs_p < 1e-6, alias
    assert "which an instrument's scale cannot do" in alias.words()
    # an angle instrument sees no length scale
    assert instrument_scale(cal, np.isfinite(d.measured) & (np.arange(6) >= 3)) is None
    path = tmp_path / "scaled.csv"
    jt.save_measurements(d, path)
    main(["diagnose", str(path), "--base", "spiral", "--effects", "lead_scale", "--out",
          str(tmp_path / "out"), "--json", str(tmp_path / "d.json")])  # fmt: skip
    assert "lead_scale: the six legs' ε agree" in capsys.readouterr().out
    doc = json.loads((tmp_path / "d.json").read_text())
    assert doc["selected_forms"] == ["lead_scale"]
    alias = doc["instrument_scale"]
    assert alias["legs_agree"] and abs(alias["common_eps"] - EPS) < 3 * alias["std"], alias
    assert "cannot tell the screws' leads" in (tmp_path / "out" / "report.md").read_text()
