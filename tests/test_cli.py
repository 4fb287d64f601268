import numpy as np
import pytest

import jaxtable as jt
from jaxtable.cli import main


def test_spiral_verb_writes_report_and_figures(tmp_path, capsys):
    rc = main(["spiral", "--out", str(tmp_path), "--samples", "200"])
    assert rc == 0
    for name in (
        "spiral.md",
        "spiral_rotation.png",
        "spiral_extension.png",
        "spiral_pose_error.png",
    ):
        assert (tmp_path / name).stat().st_size > 1000
    text = (tmp_path / "spiral.md").read_text()
    assert "largest rod rotation: leg 6, +7.360° at x = -200 mm" in text
    assert text == capsys.readouterr().out.strip() + "\n"


def test_spiral_verb_on_another_table(tmp_path):
    t = jt.replace(jt.reference_table(), lead=np.full(6, 5.0))
    path = tmp_path / "t.toml"
    jt.save_table(t, path)
    assert (
        main(["spiral", "--table", str(path), "--out", str(tmp_path / "o"), "--samples", "100"])
        == 0
    )
    text = (tmp_path / "o" / "spiral.md").read_text()
    # the extension scales with the lead: 0.2596 mm * 5 / 12.7
    assert "extension -0.1022" in text


def test_malformed_table_gives_exit_2_and_names_the_key(tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text('name = "x"\nlead = 1.0\n')
    assert main(["spiral", "--table", str(path), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "missing key(s)" in err and "home_height" in err and "bad.toml" in err


def test_simulate_then_calibrate(tmp_path, capsys):
    sim = tmp_path / "sim"
    assert (
        main(["simulate", "--n", "40", "--seed", "2", "--frame", "x=50,yaw=2", "--out", str(sim)])
        == 0
    )
    assert (sim / "data.csv").exists() and (sim / "true_table.toml").exists()
    out = tmp_path / "cal"
    assert (
        main(["calibrate", str(sim / "data.csv"), "--free", "zero_lengths", "--out", str(out)]) == 0
    )
    fitted = jt.load_table(out / "calibrated_table.toml")
    true = jt.load_table(sim / "true_table.toml")
    nominal = jt.reference_table()
    report = (out / "report.md").read_text()
    # L0 within 4σ of the truth (σ from the report; the 10 µm joint errors are unmodelled)
    sigma = [
        float(line.split("|")[4])  # | label | `key` | value | σ |
        for line in report.splitlines()
        if "| `zero_lengths[" in line
    ]
    err = np.asarray(fitted.zero_lengths) - np.asarray(true.zero_lengths)
    assert len(sigma) == 6 and np.all(np.abs(err) < 4 * np.asarray(sigma) + 0.012)
    assert not np.allclose(np.asarray(fitted.zero_lengths), np.asarray(nominal.zero_lengths))
    assert "converged: True" in report and "session 1: x +50.0" in report


def test_calibrate_says_what_it_takes_of_a_fitted_model_given_as_its_table(tmp_path, capsys):
    """A fitted model file as `calibrate --table`: the fit takes its table with the table's
    hardware effects and its zero lengths as the controller's; the command line says that
    the file's fitted effects are not in the fit and that `validate` converts with its
    `[controller]` zero lengths instead. A plain table file gets no such note."""
    nominal = jt.reference_table()
    fitted = jt.perturb_table(nominal, 3)
    model = jt.FittedModel(fitted, {"spiral": jt.Spiral.from_table(fitted),
                                    "backlash": jt.Backlash(0.01)},
                           nominal_zero_lengths=np.asarray(nominal.zero_lengths))  # fmt: skip
    path = jt.save_fitted_model(model, tmp_path / "model.toml")
    data = jt.simulate(nominal, fitted, jt.plan_random(30, 4), jt.tracker6(), seed=4)
    jt.save_measurements(data, tmp_path / "data.csv")
    for table, noted in ((path, True), (tmp_path / "plain.toml", False)):
        if not noted:
            jt.save_table(fitted, table)
        argv = ["calibrate", str(tmp_path / "data.csv"), "--table", str(table), "--free",
                "zero_lengths", "--out", str(tmp_path / "out")]  # fmt: skip
        assert main(argv) == 0
        err = capsys.readouterr().err
        assert ("is a fitted model" in err) == noted, err
        if noted:
            assert "its fitted effects (backlash) are not in this fit" in err, err
            assert "not with its [controller] ones as validate does" in err, err


def test_calibrate_refuses_malformed_csv(tmp_path, capsys):
    path = tmp_path / "bad.csv"
    path.write_text(
        "cmd_x,cmd_y,cmd_z,cmd_roll,cmd_pitch,cmd_yaw,x\n0,0,0,0,0,0,1\n0,0,oops,0,0,0,1\n"
    )
    assert main(["calibrate", str(path), "--out", str(tmp_path)]) == 2
    assert "row 2, column 'cmd_z': 'oops' is not a number" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv, said",
    [
        (["simulate", "--n", "0"], "argument --n: 0 is below the least value, 1"),
        (["simulate", "--n", "ten"], "argument --n: 'ten' is not a whole number"),
        (["simulate", "--joint-sigma", "-0.01"], "argument --joint-sigma: -0.01 is not at least 0"),
        (["simulate", "--zero-sigma", "nan"], "argument --zero-sigma: nan is not at least 0"),
        (["spiral", "--samples", "-5"], "argument --samples: -5 is below the least value, 1"),
        (["map", "--n", "0"], "argument --n: 0 is below the least value, 2"),
        (["calibrate", "d.csv", "--steps", "0"], "argument --steps: 0 is below the least"),
        (["diagnose", "--alpha", "1.5"], "argument --alpha: 1.5 is not above 0 and below 1"),
        (["diagnose", "--folds", "1"], "argument --folds: 1 is below the least value, 2"),
        (["validate", "m.toml", "d.csv", "--register", "0"], "argument --register: 0 is below"),
        (["design", "evaluate", "--leg-stiffness", "-5"], "--leg-stiffness: -5 is not above 0"),
        (["design", "evaluate", "--payload", "-10"], "argument --payload: -10 is not at least 0"),
        (["design", "evaluate", "--n-sweep", "1"], "argument --n-sweep: 1 is below the least"),
    ],
)
def test_counts_and_sizes_out_of_range_are_refused_by_the_parser(argv, said, tmp_path, capsys):
    """Counts below their least value, negative σ, stiffness or payload, a false-alarm rate
    outside (0, 1): refused before anything runs, naming the option (a count of 0 or a
    negative one stopped `simulate` and `spiral` with a traceback; a negative σ or zero
    sweep points ran)."""
    with pytest.raises(SystemExit) as stop:
        main(argv + ["--out", str(tmp_path / "out")])
    assert stop.value.code == 2 and said in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "argv, said",
    [
        (["calibrate", "d.csv", "--free", "zero_lengths,zero_lengths"], "--free: name 'zero_"),
        (
            ["calibrate", "d.csv", "--free", "spiral.lead, spiral.lead[all]"],
            "--free: 'spiral.lead' and 'spiral.lead[all]' are two forms of one field",
        ),
        (["diagnose", "--base", "backlash,backlash"], "--base: name 'backlash' is given twice"),
        (["diagnose", "--effects", "spiral,,spiral"], "--effects: name 'spiral' is given twice"),
    ],
)
def test_a_list_option_naming_one_thing_twice_is_refused(argv, said, tmp_path, capsys):
    """A name repeated in a list option, or a field free in both its forms (the shared
    column is the sum of the per-leg ones: one direction of the pair is free, which the fit
    reported as unidentifiable after the work), is refused before anything runs; the
    repeats were accepted silently."""
    assert main(argv + ["--out", str(tmp_path / "out")]) == 2
    assert said in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_the_api_refuses_the_same_repeats():
    from jaxtable._discovery.diagnose import diagnose

    table = jt.reference_table()
    data = jt.load_measurements(jt.__path__[0] + "/data/example_measurements.csv")
    with pytest.raises(ValueError, match="'zero_lengths' is given twice"):
        jt.calibrate(table, data, ("zero_lengths", "zero_lengths"))
    with pytest.raises(ValueError, match="two forms of one field"):
        jt.calibrate(
            table, data, ("thermal.alpha[all]", "thermal.alpha"), effects={"thermal": jt.Thermal()}
        )
    with pytest.raises(ValueError, match="effect 'backlash' is given twice"):
        diagnose(table, data, base=("backlash", "backlash"))


def test_one_name_given_as_a_string_is_that_name():
    """`free="zero_lengths"` is the one block, not its letters (which a repeat check would
    refuse as "'e' is given twice", and `setup` as unknown names)."""
    from jaxtable._calibration.fit import setup

    table = jt.reference_table()
    data = jt.load_measurements(jt.__path__[0] + "/data/example_measurements.csv")
    one = setup(table, data, "zero_lengths", compensated=False)
    assert one.layout.free == ("zero_lengths",)
    assert one.names == setup(table, data, ("zero_lengths",), compensated=False).names
