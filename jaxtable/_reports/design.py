"""Reports of design studies: `design evaluate` (every criterion, figures over the workspace)
and `design optimize` (start vs optimum, the design file, the Pareto front)."""

import json
from pathlib import Path

import numpy as np

from .._design.criteria import CRITERIA
from .._design.evaluate import Assessment
from .._design.optimize import DesignOptimum, ParetoFront
from .._design.variables import unit
from .._errors import POSE_COLUMNS
from .._io import save_table
from .._rotation import ARCSEC_PER_RAD
from .figures import pyplot

STIFFNESS_UNITS = "N/mm (translation block), N (coupling), N·mm/rad (rotation block)"


def evaluation_json(a: Assessment) -> dict:
    """The `design evaluate` JSON: every criterion (DESIGN.md keys) plus `stiffness_home`
    (6×6, rows/columns x, y, z, rx, ry, rz) and what it was computed on."""
    out = dict(a.values)
    out["stiffness_home"] = np.asarray(a.stiffness_home).tolist()
    out["stiffness_home_units"] = STIFFNESS_UNITS
    out["units"] = {k: c.unit for k, c in CRITERIA.items()}
    out["poses"] = len(a.poses)
    hw = a.design.hardware
    out["hardware"] = {
        "leg_stiffness_N_per_mm": np.asarray(hw.leg_stiffness).tolist(),
        "moving_mass_kg": float(hw.moving_mass(a.design.table())),
        "acceleration_m_per_s2": float(hw.acceleration),
        "velocity_mm_per_s": float(hw.velocity),
        "angular_velocity_deg_per_s": float(np.rad2deg(hw.angular_velocity)),
        "efficiency": float(hw.efficiency),
        "characteristic_length_mm": float(hw.characteristic_length),
    }
    return out


def _criteria_table(rows: list[tuple[str, list]], header: list[str]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for name, values in rows:
        lines.append(f"| {name} | " + " | ".join(values) + " |")
    return lines


def _fmt(v: float) -> str:
    return f"{v:.4g}"


def sweep_figure(a: Assessment, path: Path, n_sweep: int) -> Path:
    """Per-pose criteria along each DOF moved alone (the first 6·n_sweep poses)."""
    plt = pyplot()
    pp = a.per_pose
    panels = [
        ("lci", 1.0, "local condition index"),
        ("position_sigma", 1e3, "RMS position σ (µm)"),
        ("rotation_sigma", ARCSEC_PER_RAD, "RMS rotation σ (arcsec)"),
        ("spiral_error", 1e3, "uncompensated spiral error (µm)"),
        ("stiffness_t", 1.0, "force stiffness (N/mm)"),
        ("leg_force", 1.0, "max leg force (N)"),
        ("motor_rpm", 1.0, "max motor speed (rpm)"),
        ("margin", 1.0, "limit margin (mm)"),
    ]
    fig, axes = plt.subplots(2, 4, figsize=(15, 6.5))
    s = np.linspace(-1, 1, n_sweep)
    for ax, (key, scale, title) in zip(axes.ravel(), panels):
        y = np.asarray(pp[key][: 6 * n_sweep]).reshape(6, n_sweep) * scale
        for k in range(6):
            ax.plot(s, y[k], label=POSE_COLUMNS[k])
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("fraction of the single-DOF range")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"'{a.design.table().name}': each DOF moved alone over its range")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


def write_evaluation_report(
    a: Assessment, out: Path, workspace_text: str, n_sweep: int | None, json_path: Path
) -> str:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    figs = [sweep_figure(a, out / "design_sweeps.png", n_sweep)] if n_sweep else []
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps(evaluation_json(a), indent=2) + "\n")
    rows = [
        (f"`{k}`", [_fmt(a.values[k]), c.unit or "–", "higher" if c.sense == "max" else "lower"])
        for k, c in CRITERIA.items()
    ]
    K = np.asarray(a.stiffness_home)
    lines = [
        f"# Design evaluation: '{a.design.table().name}'",
        "",
        f"Required workspace: {workspace_text} ({len(a.poses)} poses).",
        "",
        *_criteria_table(rows, ["criterion", "value", "unit", "better"]),
        "",
        f"Stiffness at home, K = Jᵀ diag(k) J about the platform origin ({STIFFNESS_UNITS}):",
        "",
        "```",
        *("  ".join(f"{x:11.4g}" for x in row) for row in K),
        "```",
        "",
        "Formulas and units: `jaxtable._design.criteria` (README, Design studies).",
    ]
    lines += [f"\n![{f.stem}]({f.name})" for f in figs]
    text = "\n".join(lines) + "\n"
    (out / "design.md").write_text(text)
    return text


def _value_text(v) -> str:
    a = np.asarray(v, dtype=float)
    if a.ndim == 0:
        return f"{float(a):.6g}"
    return "[" + ", ".join(f"{x:.5g}" for x in a.ravel()) + "]"


def pareto_figure(front: ParetoFront, start: Assessment, path: Path) -> Path:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 4.5))
    x = [p[front.second] for p in front.points]
    y = [p[front.objective] for p in front.points]
    ax.plot(x, y, "o-", label="Pareto front (ε-constraint)")
    ax.plot(start.values[front.second], start.values[front.objective], "r*", ms=12, label="start")
    ax.set_xlabel(f"{front.second} ({CRITERIA[front.second].unit or '–'})")
    ax.set_ylabel(f"{front.objective} ({CRITERIA[front.objective].unit or '–'})")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


def write_optimization_report(
    r: DesignOptimum, out: Path, json_path: Path, front: ParetoFront | None = None
) -> str:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    table = r.design.table()
    save_table(
        table,
        out / "design.toml",
        header=f"jaxtable design optimize: {r.objective} "
        f"{'maximised' if CRITERIA[r.objective].sense == 'max' else 'minimised'} over "
        + ", ".join(r.variables),
    )
    doc = r.as_json()
    if front is not None:
        front.to_csv(out / "pareto.csv")
        pareto_figure(front, r.start, out / "pareto.png")
        doc["pareto"] = {"second": front.second, "points": front.points, "csv": "pareto.csv"}
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps(doc, indent=2) + "\n")
    sense = "maximise" if CRITERIA[r.objective].sense == "max" else "minimise"
    lines = [
        f"# Design optimisation: {sense} `{r.objective}`",
        "",
        f"{r.objective}: {r.start_value:.6g} → **{r.value:.6g}** "
        f"{CRITERIA[r.objective].unit}"
        + (
            ""
            if r.feasible
            else " (NO candidate met every constraint: the one shown violates least)"
        ),
        "",
        "| variable | start | optimum | unit |",
        "|---|---|---|---|",
    ]
    for n, (v0, v1) in r.variables.items():
        lines.append(f"| `{n}` | {_value_text(v0)} | {_value_text(v1)} | {unit(n)} |")
    if r.constraints:
        lines += ["", "| constraint | limit | value | met |", "|---|---|---|---|"]
        for c in r.constraints:
            lines.append(
                f"| `{c['name']}` {c['op']} | {c['limit']:g} | {c['value']:.5g} | "
                f"{'yes' if c['met'] else '**no**'} |"
            )
    rows = [
        (f"`{k}`", [_fmt(r.start.values[k]), _fmt(r.optimum.values[k]), c.unit or "–"])
        for k, c in CRITERIA.items()
    ]
    lines += ["", "Every criterion, start and optimum (exact, full pose set):", ""]
    lines += _criteria_table(rows, ["criterion", "start", "optimum", "unit"])
    spread = np.ptp(r.candidates) if len(r.candidates) > 1 else 0.0
    lines += [
        "",
        f"{len(r.candidates)} candidates (starts × discrete choices); their exact "
        f"{r.objective} spans {f'{spread:.3g} {CRITERIA[r.objective].unit}'.rstrip()}"
        + (" — the starts agree" if spread <= 1e-3 * max(abs(r.value), 1e-12) else ""),
        "",
        "The optimised table is `design.toml` (any verb's `--table` reads it).",
    ]
    if front is not None:
        lines += [
            "",
            f"## Pareto front: {front.objective} vs {front.second}",
            "",
            f"{len(front.points)} non-dominated points (`pareto.csv`).",
            "",
            "![pareto](pareto.png)",
        ]
    text = "\n".join(lines) + "\n"
    (out / "design_optimize.md").write_text(text)
    return text
