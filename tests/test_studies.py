"""The studies in studies/ run end to end in quick mode and write their reports.

Each test runs `python studies/<name>.py --quick --out <tmp>` in a subprocess from the
repository root and checks that the Markdown report and the figures exist and are not empty.
"""

import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import CACHE

from jaxtable._cache import MAX_BYTES

ROOT = Path(__file__).resolve().parents[1]
TIMEOUT = 600

STUDIES = {
    "paper_spiral": (
        [],
        ["spiral.md", "spiral_extension.png", "spiral_rotation.png", "spiral_pose_error.png"],
    ),
    "reconstruct_reference": ([], ["reference_reconstruction.md"]),
    "error_budget": (
        ["--big"],
        [
            "error_budget.md",
            "error_budget_big.md",
            "error_budget.png",
            "error_x_stroke.png",
            "error_map_x_y.png",
            "error_map_roll_pitch.png",
            "error_map_z_yaw.png",
        ],
    ),
    "calibration_study": ([], ["calibration_study.md", "calibration_study.png"]),
    "discovery_paper": (
        [],
        ["discovery_paper.md", "discovery_fig9_trend.png", "discovery_effect_*.png"],
    ),
    "discovery_dictionary": ([], ["discovery_dictionary.md"]),
    "discovery_power": ([], ["discovery_power.md", "discovery_power.png"]),
    "discovery_null": ([], ["discovery_null.md"]),
    "discovery_baselines": ([], ["discovery_baselines.md", "discovery_baselines.png"]),
    "validation_power": ([], ["validation_power.md", "validation_power.png"]),
    "repeatability": ([], ["repeatability.md", "repeatability.png"]),
    "design_tradeoffs": (
        [],
        ["design_tradeoffs.md", "design_lead.png", "design_geometry_maps.png"],
    ),
}


def run_quick(name: str, extra: list, out: Path) -> subprocess.CompletedProcess:
    cmd = [sys.executable, f"studies/{name}.py", "--quick", "--out", str(out), *extra]
    # the persistent compilation cache the test suite uses (conftest.CACHE, which
    # $JAXTABLE_TEST_CACHE moves: a suite timed from an empty cache runs its studies on it
    # too), so that reruns do not recompile the studies' fits
    env = os.environ | {
        "JAX_COMPILATION_CACHE_DIR": str(CACHE),
        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0.5",
        # the size limit that makes JAX lock the shared cache (see jaxtable/_cache.py)
        "JAX_COMPILATION_CACHE_MAX_SIZE": str(MAX_BYTES),
    }
    return subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=TIMEOUT)


# quick runs that take more than ~90 s from a cold compilation cache on 2 cores (about
# 140 s and 190 s: their fits and diagnose compile for every data shape; the design study
# about 130 s: its optimisations compile once each; the null study's 4 diagnoses repeat
# what the default suite's 20-seed null test does; the baselines' 3 diagnoses and GP fits
# what test_gp and test_diagnose check)
SLOW = {
    "calibration_study",
    "discovery_paper",
    "discovery_dictionary",
    "discovery_power",
    "discovery_null",
    "discovery_baselines",
    "design_tradeoffs",
}


@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.slow) if n in SLOW else n for n in STUDIES]
)
def test_study_quick(name, tmp_path):
    extra, expected = STUDIES[name]
    r = run_quick(name, extra, tmp_path)
    assert r.returncode == 0, f"{name} failed:\n{r.stdout[-3000:]}\n{r.stderr[-5000:]}"
    for pattern in expected:
        found = sorted(tmp_path.glob(pattern))
        assert found, f"{name}: no {pattern} in {sorted(p.name for p in tmp_path.iterdir())}"
        for path in found:
            assert path.stat().st_size > 0, f"{name}: {path.name} is empty"
    for md in tmp_path.glob("*.md"):
        assert md.read_text().startswith("# "), f"{name}: {md.name} has no title"


def test_studies_use_public_api_only():
    """No study (except the benchmark wrapper) reaches into jaxtable's private modules."""
    for name in STUDIES:
        text = (ROOT / "studies" / f"{name}.py").read_text()
        assert "jaxtable._" not in text and "from jaxtable import _" not in text, name
