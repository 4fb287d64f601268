import numpy as np

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
