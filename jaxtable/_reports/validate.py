"""The validation report: Markdown, JSON and residual figures (against stop index and
against each commanded pose coordinate) of `jaxtable validate`."""

import json
from pathlib import Path

import numpy as np

from .. import _params as params
from .._calibration.outliers import BLUNDER_WORDS, repeat_words
from .._calibration.validate import Validation
from .figures import pyplot

_UNIT = np.array([1e3] * 3 + [np.rad2deg(1.0) * 3600] * 3)  # µm, arcsec
_UNIT_NAME = ["µm"] * 3 + ["arcsec"] * 3


def residual_figures(v: Validation, out: Path) -> list[Path]:
    """`residuals_by_stop.png` (each measured column against the stop index, registered
    rows marked) and `residuals_by_pose.png` (against each commanded pose coordinate)."""
    plt = pyplot()
    res = v.residual
    cols = [k for k in range(6) if np.isfinite(res[:, k]).any()]
    idx = np.arange(1, len(res) + 1)
    reg = v.registered
    fig, axes = plt.subplots(len(cols), 1, figsize=(8, 1.8 * len(cols) + 0.8), sharex=True)
    axes = np.atleast_1d(axes)
    for ax, k in zip(axes, cols):
        y = res[:, k] * _UNIT[k]
        ax.plot(idx[~reg], y[~reg], ".", ms=3, color="C0", label="predicted")
        if reg.any():
            ax.plot(idx[reg], y[reg], ".", ms=3, color="0.6", label="used to register")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_ylabel(f"{params.POSE[k]} ({_UNIT_NAME[k]})", fontsize=8)
    axes[0].legend(fontsize=7, loc="upper right")
    axes[-1].set_xlabel("stop (row of the data file)")
    fig.suptitle("measured − predicted reading", fontsize=10)
    fig.tight_layout()
    p1 = out / "residuals_by_stop.png"
    fig.savefig(p1, dpi=100)
    plt.close(fig)

    cmd = params.pose_to_file(v.data.cmd_pose)
    shown = ~reg if (~reg).any() else np.ones_like(reg)  # every row registered: the fit's
    fig, axes = plt.subplots(2, 3, figsize=(12, 6.5), sharey=True)
    for c, ax in enumerate(axes.ravel()):
        for k in cols:
            ok = shown & np.isfinite(res[:, k])
            y = res[ok, k] * _UNIT[k]
            scale = (np.std(y) if ok.sum() > 1 else 0.0) or 1.0
            ax.plot(cmd[ok, c], y / scale, ".", ms=2.5, label=params.POSE[k])
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel(f"commanded {params.POSE[c]} ({'mm' if c < 3 else 'deg'})")
    axes[0, 0].set_ylabel("residual / its RMS")
    axes[1, 0].set_ylabel("residual / its RMS")
    axes[0, 0].legend(fontsize=7, ncol=2)
    fig.suptitle(
        ("predicted rows" if (~reg).any() else "every row registered (a fit, not a prediction)")
        + ": residual of each measured column against the pose",
        fontsize=10,
    )
    fig.tight_layout()
    p2 = out / "residuals_by_pose.png"
    fig.savefig(p2, dpi=100)
    plt.close(fig)
    return [p1, p2]


def markdown(v: Validation, model_source: str, data_source: str, figures) -> str:
    kind = "prediction" if v.is_prediction else "fit (every row registered a frame)"
    lines = [
        f"# Validation of {model_source} on {data_source}",
        "",
        f"Result: **{kind}**. {'Rows' if v.stops is None else 'Stops'} used to register a "
        f"new session's frame: {v.rows_registered}; predicted: {v.rows_predicted}"
        + ("." if v.stops is None else " (a stop read several times is the mean of its readings)."),
        "",
        "| column | RMS (measured − predicted) | RMS / the fit's noise σ |",
        "|---|---|---|",
        *[
            f"| {c} | {r:.4g} {'mm' if c in params.XYZ else 'deg'} | "
            + (f"{v.noise_ratio[c]:.3g}" if c in v.noise_ratio else "not in the model file")
            + " |"
            for c, r in v.rms.items()
        ],
    ]
    if v.leg_rms is not None:
        lines.append(f"| leg lengths (implied − model) | {v.leg_rms:.4g} mm | |")
    if v.noise_ratio:
        lines += ["", v.noise_words() + "."]
    if v.repeated:
        lines += ["", repeat_words(v.repeated) + "; neither registered nor scored."]
    if v.stops is not None:
        lines += ["", v.stops.words() + "."]
    if v.set_aside:
        lines += [
            "",
            f"{len(v.set_aside)} reading(s) no table could have produced ({BLUNDER_WORDS}) "
            "were neither registered nor scored: "
            + "; ".join(g.words() for g in v.set_aside[:10])
            + ("; ..." if len(v.set_aside) > 10 else "")
            + ".",
        ]
    lines += ["", "Instrument frames (pose of the base frame in the instrument frame):", ""]
    for label, f in v.frames.items():
        pose = ", ".join(
            f"{c} {x:+.4f} {'mm' if k < 3 else '°'}"
            for k, (c, x) in enumerate(zip(params.POSE, f["pose"]))
        )
        how = (
            "stored in the model"
            if f["source"] == "stored"
            else f"registered on {f['rows_registered']} row(s)"
            + (" with a drift, at the session's first row" if f.get("drift") else "")
        )
        lines.append(f"- session {label}: {how}; {pose}")
    drift = v.drift_lines() + v.trend_lines()
    if drift:
        lines += [""] + [f"- {d}" for d in drift]
    lines += [""] + [f"![{Path(p).stem}]({Path(p).name})" for p in figures] + [""]
    return "\n".join(lines)


def write_validation_report(
    v: Validation, out, model_source: str, data_source: str, json_path=None
) -> list[Path]:
    """Write report.md, the residual figures and (optionally) the JSON; return the paths."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    figures = residual_figures(v, out)
    (out / "report.md").write_text(markdown(v, model_source, data_source, figures))
    paths = [out / "report.md"] + figures
    if json_path is not None:
        json_path = Path(json_path)
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(v.as_json(), indent=2))
        paths.append(json_path)
    return paths
