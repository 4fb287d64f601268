"""Figures and Markdown for workspace error maps (shared by `jaxtable map` and
studies/error_budget.py)."""

from pathlib import Path

import numpy as np

from .._analysis.errormap import TARGET_MM, ErrorMap, Grid, error_map
from .._analysis.tolerances import SOURCES, Tolerances
from .._errors import POSE_COLUMNS
from .._rotation import ARCSEC_PER_RAD
from .._table import Table
from .figures import pyplot

LABELS = list(SOURCES) + ["total"]


def _axis(grid: Grid, k: int):
    a = grid.axes[k]
    v = np.asarray(grid.values[k])
    if a >= 3:
        return np.rad2deg(v), f"{POSE_COLUMNS[a]} (deg)"
    return v, f"{POSE_COLUMNS[a]} (mm)"


def slice_figures(table: Table, emap: ErrorMap, out: Path, stem: str) -> list[Path]:
    """Heatmaps over a 2-D slice: total translation and rotation σ (compensated), spiral
    bias when uncompensated, condition number, and the dominant source."""
    plt = pyplot()
    g = emap.grid
    x, xl = _axis(g, 0)
    y, yl = _axis(g, 1)
    mask = ~emap.reachable
    tr = emap.translation(True)
    panels = [
        ("translation σ, total (mm)", tr[..., -1], "viridis"),
        ("rotation σ, total (arcsec)", emap.rotation(True)[..., -1] * ARCSEC_PER_RAD, "viridis"),
        ("spiral bias if uncompensated (mm)", np.linalg.norm(emap.bias[..., :3], axis=-1), "magma"),
        ("condition number of the Jacobian", emap.cond, "cividis"),
    ]
    fig, axes = plt.subplots(1, 5, figsize=(22, 4.2))
    for ax, (title, z, cmap) in zip(axes, panels):
        im = ax.pcolormesh(x, y, np.ma.masked_where(mask, z).T, shading="auto", cmap=cmap)
        fig.colorbar(im, ax=ax)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel(xl)
        ax.set_ylabel(yl)
    dom = np.argmax(tr[..., :-1], axis=-1)
    ax = axes[-1]
    cm = plt.get_cmap("tab10", len(SOURCES))
    im = ax.pcolormesh(
        x,
        y,
        np.ma.masked_where(mask, dom).T,
        shading="auto",
        cmap=cm,
        vmin=-0.5,
        vmax=len(SOURCES) - 0.5,
    )
    cb = fig.colorbar(im, ax=ax, ticks=range(len(SOURCES)))
    cb.ax.set_yticklabels(SOURCES, fontsize=7)
    ax.set_title("dominant source (translation)", fontsize=9)
    ax.set_xlabel(xl)
    ax.set_ylabel(yl)
    fixed = ", ".join(
        f"{c} {np.rad2deg(v) if k >= 3 else v:g}"
        for k, (c, v) in enumerate(zip(POSE_COLUMNS, g.fixed))
        if k not in g.axes
    )
    fig.suptitle(
        f"{table.name}: linear error propagation over the {POSE_COLUMNS[g.axes[0]]}-"
        f"{POSE_COLUMNS[g.axes[1]]} slice ({fixed}); grey = unreachable",
        fontsize=10,
    )
    fig.tight_layout()
    path = out / f"{stem}.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return [path]


def x_stroke_figure(
    table: Table, tolerances: Tolerances, out: Path, x_range: float = 200.0
) -> Path:
    """Error along the paper's Fig. 9 axis (x every 2.5 mm): σ per source, and the spiral
    bias of an uncompensated controller, against the ±0.2 mm target."""
    plt = pyplot()
    xs = np.linspace(-x_range, x_range, 161)
    poses = np.zeros((len(xs), 6))
    poses[:, 0] = xs
    emap, _ = error_map(table, tolerances, poses)  # the small maps' compiled size (256 rows)
    tr = emap.translation(True)
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4))
    for k, name in enumerate(LABELS):
        a1.plot(
            xs,
            tr[:, k],
            lw=2.2 if name == "total" else 1.2,
            color="k" if name == "total" else None,
            label=name,
        )
    a1.set_ylabel("RMS translation error σ (mm)")
    a1.set_title("compensated: random errors (1σ)", fontsize=10)
    for c in range(3):
        a2.plot(xs, emap.bias[:, c], label=f"spiral bias {POSE_COLUMNS[c]}")
        a2.fill_between(
            xs,
            emap.bias[:, c] - 2 * emap.std[:, -1, c],
            emap.bias[:, c] + 2 * emap.std[:, -1, c],
            alpha=0.15,
        )
    for s in (-1, 1):
        a2.axhline(s * TARGET_MM, color="r", ls="--", lw=1)
    a2.set_ylabel("translation error (mm)")
    a2.set_title("uncompensated: spiral bias ± 2σ; red: ±0.2 mm target", fontsize=10)
    for ax in (a1, a2):
        ax.set_xlabel("commanded x (mm)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"{table.name}: error along the x stroke (paper Fig. 9 axis)", fontsize=10)
    fig.tight_layout()
    path = out / "error_x_stroke.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def budget_chart(summary: dict, out: Path, stem: str = "error_budget") -> Path:
    """Bars: max and 95th-percentile translation / rotation error per source and totals."""
    plt = pyplot()
    names = list(summary["sources"])
    S = summary["sources"]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.2))
    idx = np.arange(len(names))
    for ax, key, unit in ((a1, "trans", "mm"), (a2, "rot", "arcsec")):
        ax.bar(idx - 0.2, [S[n][f"{key}_max_{unit}"] for n in names], 0.4, label="max")
        ax.bar(idx + 0.2, [S[n][f"{key}_p95_{unit}"] for n in names], 0.4, label="95th pct")
        ax.set_xticks(idx, names, rotation=30, ha="right", fontsize=8)
        ax.set_yscale("log")
        ax.set_ylabel(f"RMS {'translation' if key == 'trans' else 'rotation'} error ({unit})")
        ax.grid(alpha=0.3, axis="y")
        ax.legend(fontsize=8)
    a1.axhline(TARGET_MM, color="r", ls="--", lw=1)
    fig.suptitle(f"Error budget over {summary['reachable']} reachable poses", fontsize=10)
    fig.tight_layout()
    path = out / f"{stem}.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def summary_markdown(summary: dict, title: str) -> str:
    lines = [
        f"### {title}",
        "",
        f"{summary['reachable']} reachable of {summary['poses']} poses; largest condition "
        f"number {summary['cond_max']:.2f}. ±{TARGET_MM} mm target (|bias| + 2σ per translation "
        f"component) met at {100 * summary['meets_target_compensated']:.1f} % of poses with "
        f"the spiral compensated, {100 * summary['meets_target_uncompensated']:.1f} % without.",
        "",
        "| source | translation max (mm) | translation 95 % (mm) | rotation max (arcsec) "
        "| rotation 95 % (arcsec) |",
        "|---|---|---|---|---|",
    ]
    for name, v in summary["sources"].items():
        lines.append(
            f"| {name} | {v['trans_max_mm']:.4f} | {v['trans_p95_mm']:.4f} | "
            f"{v['rot_max_arcsec']:.2f} | {v['rot_p95_arcsec']:.2f} |"
        )
    lines.append("")
    return "\n".join(lines)


def write_map_report(
    table: Table, tol: Tolerances, emap: ErrorMap, summary: dict, out, dofs, n: int
) -> str:
    """Figures of a 2-D slice map (`map_<a>_<b>.png`, the x stroke, the budget chart) and
    `map.md` into `out`; returns the Markdown."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"map_{dofs[0]}_{dofs[1]}"
    slice_figures(table, emap, out, stem)
    x_stroke_figure(table, tol, out)
    budget_chart(summary, out)
    text = "\n".join(
        [
            f"# Error map: {table.name}",
            "",
            "Tolerances (file units): "
            + ", ".join(f"{k} = {v:g}" for k, v in tol.as_dict().items()),
            "",
            summary_markdown(summary, f"{dofs[0]}-{dofs[1]} slice, {n} x {n} poses"),
            f"Figures: {stem}.png, error_x_stroke.png, error_budget.png",
            "",
        ]
    )
    (out / "map.md").write_text(text)
    return text
