"""The calibration report: the fitted table file, the Markdown report (fit statistics,
instrument frames, parameters with σ under physical names, held-out check) and, with a
posterior, its corner plot and predictive bands. Shared by `jaxtable calibrate`."""

import math
from pathlib import Path

import numpy as np

from .._calibration.fit import Calibration, Setup
from .._calibration.heldout import UNDEFINED_WORDS, heldout_rms, make_folds
from .._calibration.measurements import Measurements
from .._calibration.model_file import fitted_model, save_fitted_model
from .._calibration.posterior import PosteriorResult, PredictiveBands
from .._discovery.structure import StructureTest
from .._table import Table
from .posterior import corner_plot, plot_bands


def _frames(cal: Calibration, data: Measurements) -> str:
    return "\n".join(
        f"- session {lab}: "
        + ", ".join(f"{c} {v:+.4f}" for c, v in zip("x y z".split(), cal.frame[k, :3]))
        + " mm, "
        + ", ".join(
            f"{c} {np.rad2deg(v):+.5f}°" for c, v in zip("roll pitch yaw".split(), cal.frame[k, 3:])
        )
        for k, lab in enumerate(data.sessions)
    )


def write_calibration_report(
    nominal: Table,
    st: Setup,
    cal: Calibration,
    data: Measurements,
    out,
    source: str,
    *,
    posterior: PosteriorResult | None = None,
    bands: PredictiveBands | None = None,
    structure: StructureTest | None = None,
) -> list[Path]:
    """Write `calibrated_table.toml` and `report.md` (and `corner.png`, `bands.png` with a
    posterior) into `out`; returns the paths written. `structure`: the structure test of
    the fit's residuals, reported when given."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    free = ", ".join(st.layout.free)
    save_fitted_model(
        fitted_model(cal, nominal, data.sessions),
        out / "calibrated_table.toml",
        header=f"Calibrated from {source} (free: {free}); joint centres are fitted modulo "
        "rigid motions where the instrument frame was estimated (see report.md).",
    )
    labels = cal.labels or cal.names
    rows = [
        f"| {lab} | `{key}` | {v:+.5g} | {s:.3g} |"
        for lab, key, v, s in zip(labels, cal.names, cal.value, cal.std)
    ]
    folds = make_folds(len(data), 5, 0, strata=data.session_index)
    text = "\n".join(
        [
            f"# Calibration of {nominal.name} from {source}",
            "",
            "```",
            cal.report(),
            "```",
            "",
            "Instrument frame (pose of the base frame in the instrument frame) per session:",
            "",
            _frames(cal, data),
            "",
            "| parameter (change from nominal) | key | value | σ |",
            "|---|---|---|---|",
            *rows,
            "",
            "Held-out check (5-fold: each fifth of the rows predicted by the fit to the rest): "
            + (
                f"RMS {held:.3f} σ, against {cal.rms_sigma_after:.3f} σ on the fitted rows "
                "(1.0 = the instrument noise)."
                if math.isfinite(held := heldout_rms(cal, folds, st.mask))
                else f"not defined: {UNDEFINED_WORDS}."
            ),
            "",
            *(
                []
                if structure is None
                else [
                    f"Residual structure: {structure.words()} (neighbour-agreement test at "
                    f"false-alarm rate {structure.alpha:g}, independent of σ's scale"
                    + ("; `jaxtable diagnose` names library causes" if structure.structure else "")
                    + ").",
                    "",
                ]
            ),
        ]
    )
    paths = [out / "calibrated_table.toml", out / "report.md"]
    if posterior is not None:
        corner_plot(posterior, out / "corner.png")
        paths.append(out / "corner.png")
        parts = ["", "## Posterior (emcee)", "", "```", posterior.summary(), "```", ""]
        parts += ["![corner](corner.png)", ""]
        if bands is not None:
            plot_bands(bands, out / "bands.png")
            paths.append(out / "bands.png")
            parts += [
                "Posterior-predictive pose error along the x stroke (nominal controller, "
                "sampled tables):",
                "",
                "![bands](bands.png)",
                "",
            ]
        text += "\n".join(parts)
    (out / "report.md").write_text(text)
    return paths
