"""The parameter vocabulary: one spelling for parameters, their element keys and physical
labels, and reading / replacing them in a model."""

import numpy as np
import pytest

import jaxtable as jt
from jaxtable import _params as params


def test_default_free_set_is_the_42_geometric_parameters(table):
    assert jt.GEOMETRY == ("base_joints", "platform_joints", "zero_lengths")
    assert sum(np.size(getattr(table, n)) for n in jt.GEOMETRY) == 42
    assert set(params.PAPER_42) == set(jt.GEOMETRY)


def test_split_and_effect_parameters():
    assert params.split("spiral.lead") == ("spiral", "lead")
    assert params.split("zero_lengths") == (None, "zero_lengths")
    assert params.effect_parameters("periodic_lead") == ("periodic_lead.a", "periodic_lead.b")


def test_get_and_replace_round_trip_without_mutation(table):
    effects = {"spiral": jt.Spiral(12.7), "lead_scale": jt.LeadScale(1e-4)}
    new_l0 = np.asarray(table.zero_lengths) + 0.01
    t2, e2 = params.replace(
        table, effects, {"zero_lengths": new_l0, "lead_scale.eps": 2e-4 + 0 * new_l0}
    )
    np.testing.assert_allclose(np.asarray(params.get(t2, e2, "zero_lengths")), new_l0)
    np.testing.assert_allclose(np.asarray(params.get(t2, e2, "lead_scale.eps")), 2e-4)
    # the inputs are unchanged
    np.testing.assert_allclose(np.asarray(effects["lead_scale"].eps), 1e-4)
    assert float(table.zero_lengths[0]) == pytest.approx(float(new_l0[0]) - 0.01)


def test_check_names_the_bad_parameter(table):
    with pytest.raises(ValueError, match="no effect 'thermal'"):
        params.check(table, {}, ["thermal.alpha"])
    with pytest.raises(ValueError, match="unknown parameter 'legs'"):
        params.check(table, {}, ["legs"])
    with pytest.raises(ValueError, match="no array field 'k'"):
        params.check(table, {"spiral": jt.Spiral(1.0)}, ["spiral.k"])


def test_element_keys_and_labels_are_physical():
    assert params.element_keys("base_joints", (6, 3))[4] == "base_joints[2].y"
    assert params.element_keys("zero_lengths", (6,))[2] == "zero_lengths[3]"
    cases = {
        "base_joints[2].y": "base joint 2 y",
        "platform_joints[6].z": "platform joint 6 z",
        "zero_lengths[3]": "leg 3 zero length L0",
        "spiral.lead[1]": "spiral lead, leg 1",
        "frame[2].yaw": "instrument frame (session 2) yaw",
        "target.z": "target offset z",
        "rehoming.offsets[1].3": "rehoming offsets, session 2, leg 3",
    }
    for key, label in cases.items():
        assert params.label(key) == label


def test_gauge_label_names_the_largest_joint_displacements():
    basis = np.zeros((18, 2))
    basis[7, 0], basis[2, 0] = 0.8, -0.6  # joint 3 y, joint 1 z
    text = params.gauge_label("base_joints", 0, basis)
    assert text.startswith("base joints: non-rigid mode 1")
    assert "+0.80 joint 3 y" in text and "-0.60 joint 1 z" in text


def test_calibration_reports_physical_labels(table):
    true = jt.perturb_table(table, 3)
    data = jt.simulate(table, true, jt.plan_random(30, 3), jt.tracker6(), seed=3)
    st = jt.setup(table, data)
    assert len(st.labels) == len(st.names)
    assert "leg 1 zero length L0" in st.labels
    assert any(s.startswith("base joints: non-rigid mode") for s in st.labels)
    assert "instrument frame (session 1) x" in st.labels


def test_one_leg_forms_are_a_cylinder_s_own_defects_on_that_leg_alone():
    """A defect of one cylinder's screw or nut can be fitted on that leg alone; the effects
    every cylinder has (the spiral, thermal expansion, compliance) cannot."""
    assert params.leg_forms("lead_scale") == tuple(f"lead_scale[{i}]" for i in range(1, 7))
    assert len(params.leg_forms("backlash")) == len(params.leg_forms("periodic_lead")) == 6
    for effect in ("spiral", "thermal", "compliance", "rehoming"):
        assert params.leg_forms(effect) == ()
    assert params.leg_of("lead_scale[3]") == 3
    assert params.leg_of("thermal[all]") is None and params.leg_of("lead_scale") is None
    assert params.form_effect("periodic_lead[2]") == "periodic_lead"
    assert params.effect_parameters("periodic_lead[2]") == (
        "periodic_lead.a[2]",
        "periodic_lead.b[2]",
    )
    assert params.form_label("backlash[4]") == "backlash (leg 4 alone)"
    keys = [f"lead_scale.eps[{i}]" for i in range(1, 7)] + ["thermal.alpha[3]"]
    assert params.form_keys(keys, "lead_scale[3]") == ["lead_scale.eps[3]"]
    assert params.form_keys(keys, "lead_scale") == keys[:6]
    # a one-leg form joins the effect's other legs; the per-leg form replaces them all
    model = ["thermal[all]", "lead_scale[2]"]
    assert params.with_form(model, "lead_scale[5]") == model + ["lead_scale[5]"]
    assert params.with_form(model + ["lead_scale[5]"], "lead_scale") == [
        "thermal[all]",
        "lead_scale",
    ]
    assert params.with_form(model, "thermal") == ["lead_scale[2]", "thermal"]
