import numpy as np
import pytest

import jaxtable as jt
from jaxtable._io import table_to_toml


def leaves(t):
    names = [
        "base_joints",
        "platform_joints",
        "base_axes",
        "platform_axes",
        "zero_lengths",
        "home_height",
        "lead",
        "hand",
        "stroke",
        "joint_angle_limit",
        "platform_mass",
        "platform_cog",
    ]
    return {n: np.asarray(getattr(t, n)) for n in names}


def test_round_trip_is_exact(table, tmp_path):
    path = tmp_path / "t.toml"
    jt.save_table(table, path)
    back = jt.load_table(path)
    for name, value in leaves(table).items():
        np.testing.assert_array_equal(leaves(back)[name], value, err_msg=name)
    assert back.name == table.name


def test_zero_lengths_default_to_home_leg_lengths(table, tmp_path):
    text = "\n".join(
        line for line in table_to_toml(table).splitlines() if not line.startswith("zero_lengths")
    )
    path = tmp_path / "t.toml"
    path.write_text(text)
    t = jt.load_table(path)
    np.testing.assert_allclose(
        np.asarray(t.zero_lengths), np.asarray(jt.leg_lengths(t, np.zeros(6))), rtol=0, atol=1e-12
    )


def test_per_leg_lead_and_hand(table, tmp_path):
    text = table_to_toml(table)
    text = text.replace("lead = 12.7", "lead = [12.7, 12.7, 10.0, 10.0, 0.0, 5.0]")
    text = text.replace(
        'hand = "right"', 'hand = ["right", "left", "right", "left", "right", "right"]'
    )
    path = tmp_path / "t.toml"
    path.write_text(text)
    t = jt.load_table(path)
    np.testing.assert_array_equal(np.asarray(t.signed_lead), [12.7, -12.7, 10, -10, 0, 5])
    jt.save_table(t, tmp_path / "u.toml")
    np.testing.assert_array_equal(
        np.asarray(jt.load_table(tmp_path / "u.toml").signed_lead), np.asarray(t.signed_lead)
    )


def _broken(table, tmp_path, old, new):
    text = table_to_toml(table)
    assert old in text
    path = tmp_path / "bad.toml"
    path.write_text(text.replace(old, new, 1))
    return path


@pytest.mark.parametrize(
    "old, new, words",
    [
        ("home_height = ", "height = ", ["missing", "home_height"]),
        ("stroke = ", "strok = ", ["missing", "stroke"]),
        ("name = ", "colour = 1\nname = ", ["unknown", "colour"]),
        (
            "    [-0.9848077530122081, -0.17364817766693003, 0.0],",
            "    [0.0, 0.0, 0.0],",
            ["base_axes row 1", "zero"],
        ),
        (
            "    [-0.9848077530122081, -0.17364817766693003, 0.0],",
            "    [-0.5, -0.1, 0.0],",
            ["base_axes row 1", "unit"],
        ),
        (
            "    [-0.9848077530122081, -0.17364817766693003, 0.0],",
            "    [-0.9848, 0.1736],",
            ["base_axes", "shape"],
        ),
        ('hand = "right"', 'hand = "up"', ["hand", "leg 1"]),
        ("lead = 12.7", "lead = 'fast'", ["lead"]),
        ("stroke = [600.0, 1060.0]", "stroke = [900.0, 1060.0]", ["outside the stroke", "leg 1"]),
        ("name = ", "name = = ", ["not valid TOML"]),
    ],
)
def test_malformed_file_is_refused_by_name(table, tmp_path, old, new, words):
    path = _broken(table, tmp_path, old, new)
    with pytest.raises(jt.TableFileError) as e:
        jt.load_table(path)
    for w in words:
        assert w in str(e.value), str(e.value)
    assert str(path) in str(e.value)


def test_axis_parallel_to_leg_at_home_is_refused(table, tmp_path):
    b = np.asarray(table.base_joints)[2]
    a = np.asarray(table.platform_joints)[2] + np.array([0, 0, float(table.home_height)])
    u = (a - b) / np.linalg.norm(a - b)
    old = "    [-0.17364817766693033, -0.984807753012208, 0.0],"  # platform axis of leg 3
    path = _broken(table, tmp_path, old, "    [" + ", ".join(repr(float(v)) for v in u) + "],")
    with pytest.raises(jt.TableFileError, match=r"platform_axes row 3 \(leg 3\) is parallel"):
        jt.load_table(path)


def test_missing_file(tmp_path):
    with pytest.raises(jt.TableFileError, match="not found"):
        jt.load_table(tmp_path / "nope.toml")
