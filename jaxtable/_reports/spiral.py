"""The passive spiral term of a table: the paper's Fig. 5 and 6 re-drawn, and the pose error
the term causes with and without compensation, along the x stroke and over the workspace.

Shared by `jaxtable spiral` and `studies/paper_spiral.py`.
"""

from pathlib import Path

import numpy as np

from .._analysis.workspaces import Workspace
from .._api import (
    actuator_command,
    forward,
    pose_error,
    reachable,
    rod_rotation,
    spiral_extension,
)
from .._errors import POSE_COLUMNS
from .._rotation import ARCSEC_PER_RAD
from .._table import Table
from .figures import pyplot


def _pose_error(table: Table, poses: np.ndarray, compensate: bool) -> np.ndarray:
    """`pose_error` of the actual pose against the desired one (translation mm, rotation
    vector rad) when the controller commands with/without compensation and the hardware has
    its passive term (exact forward kinematics, spiral inside)."""
    cmd = actuator_command(table, poses, compensated=compensate)
    return np.asarray(pose_error(forward(table, cmd), poses))


def _norms(err: np.ndarray):
    return np.linalg.norm(err[..., :3], axis=-1), np.linalg.norm(err[..., 3:], axis=-1)


def spiral_analysis(
    table: Table,
    workspace: Workspace = Workspace(),
    n_random: int = 20000,
    x_range: float = 200.0,
    n_x: int = 161,
) -> dict:
    """Numbers behind the report. Pose sets are limited to the poses the table can reach."""
    xs = np.linspace(-x_range, x_range, n_x)
    line = np.zeros((n_x, 6))
    line[:, 0] = xs
    out = {"xs": xs, "line_reachable": bool(np.all(np.asarray(reachable(table, line))))}
    out["twist_deg"] = np.rad2deg(np.asarray(rod_rotation(table, line)))
    out["extension_mm"] = np.asarray(spiral_extension(table, line))
    out["line_err_raw"] = _pose_error(table, line, compensate=False)
    out["line_err_comp"] = _pose_error(table, line, compensate=True)

    sweeps = workspace.sweeps()
    box = workspace.box_samples(n_random)
    sets = {f"{c} alone": sweeps[k] for k, c in enumerate(POSE_COLUMNS)}
    sets["all six (box)"] = box
    rows = []
    for name, poses in sets.items():
        ok = np.asarray(reachable(table, poses))
        p = poses[ok]
        raw = _pose_error(table, p, compensate=False)
        comp = _pose_error(table, p, compensate=True)
        ext = np.abs(np.asarray(spiral_extension(table, p)))
        t_raw, r_raw = _norms(raw)
        t_comp, r_comp = _norms(comp)
        k = int(np.argmax(t_raw))
        rows.append(
            dict(
                worst_pose_ext=p[int(np.argmax(ext.max(axis=1)))],
                set=name,
                n=int(ok.sum()),
                n_total=len(poses),
                max_ext_mm=float(ext.max()),
                max_trans_raw_mm=float(t_raw.max()),
                max_rot_raw_arcsec=float(r_raw.max() * ARCSEC_PER_RAD),
                max_trans_comp_mm=float(t_comp.max()),
                max_rot_comp_arcsec=float(r_comp.max() * ARCSEC_PER_RAD),
                worst_pose=p[k],
            )
        )
    out["rows"] = rows
    return out


def _fmt_pose(p):
    parts = []
    for k, c in enumerate(POSE_COLUMNS):
        v = p[k] if k < 3 else np.rad2deg(p[k])
        if abs(v) > 1e-9:
            parts.append(f"{c} {v:+.1f}{'' if k < 3 else '°'}")
    return ", ".join(parts) or "home"


def markdown(table: Table, a: dict, workspace: Workspace) -> str:
    tw, ext = a["twist_deg"], a["extension_mm"]
    i, k = np.unravel_index(np.abs(tw).argmax(), tw.shape)
    t_raw, r_raw = _norms(a["line_err_raw"])
    t_comp, r_comp = _norms(a["line_err_comp"])
    lines = [
        f"# Passive spiral motion: {table.name}",
        "",
        f"Lead {np.asarray(table.lead).tolist()} mm/rev, hand "
        f"{['right' if h > 0 else 'left' for h in np.asarray(table.hand)]}.",
        "Rod rotation: right-hand about the leg axis (base -> platform); positive = "
        "counter-clockwise seen from the platform end.",
        "",
        "## Along the x stroke (paper Fig. 5, 6)",
        "",
        f"- largest rod rotation: leg {k + 1}, {tw[i, k]:+.3f}° at x = {a['xs'][i]:+.0f} mm",
        "- at x = {:+.0f} mm: rotation {} deg; extension {} mm".format(
            a["xs"][0],
            " ".join(f"{v:+.3f}" for v in tw[0]),
            " ".join(f"{v:+.4f}" for v in ext[0]),
        ),
        f"- pose error without compensation: max |translation| {t_raw.max():.4f} mm, "
        f"max |rotation| {r_raw.max() * ARCSEC_PER_RAD:.2f} arcsec",
        f"- with compensation (Δl* = Δl − Δl2): {t_comp.max():.2e} mm, "
        f"{r_comp.max() * ARCSEC_PER_RAD:.2e} arcsec",
        "",
        "## Over the workspace",
        "",
        f"Workspace: {workspace.describe()} (unreachable poses excluded). Pose error = exact "
        "forward kinematics with the passive term inside, minus the commanded pose.",
        "",
        "| pose set | poses | max passive extension (mm) | max translation error, "
        "uncompensated (mm) | max rotation error, uncompensated (arcsec) | worst pose "
        "| max translation error, compensated (mm) | max rotation error, compensated (arcsec) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in a["rows"]:
        lines.append(
            f"| {r['set']} | {r['n']}/{r['n_total']} | {r['max_ext_mm']:.3f} | "
            f"{r['max_trans_raw_mm']:.3f} | {r['max_rot_raw_arcsec']:.1f} | "
            f"{_fmt_pose(r['worst_pose'])} | {r['max_trans_comp_mm']:.1e} | "
            f"{r['max_rot_comp_arcsec']:.1e} |"
        )
    worst = max(a["rows"], key=lambda r: r["max_trans_raw_mm"])
    worst_ext = max(a["rows"], key=lambda r: r["max_ext_mm"])
    top = max(worst["max_trans_raw_mm"], worst_ext["max_ext_mm"])
    verdict = (
        "reaches a millimetre or more"
        if top >= 1.0
        else f"approaches a millimetre (tenths of a millimetre up to {top:.2f} mm)"
        if top >= 0.5
        else "stays at tenths of a millimetre or less, nowhere near a millimetre"
    )
    lines += [
        "",
        '## Does "millimetre order" hold?',
        "",
        f"In this workspace the passive term {verdict}. Largest uncompensated translation "
        f"error: {worst['max_trans_raw_mm']:.3f} mm ({worst['set']}, at "
        f"{_fmt_pose(worst['worst_pose'])}); largest passive leg extension "
        f"{worst_ext['max_ext_mm']:.3f} mm ({worst_ext['set']}, at "
        f"{_fmt_pose(worst_ext['worst_pose_ext'])}); along the paper's x stroke "
        f"{t_raw.max():.3f} mm.",
        "",
    ]
    return "\n".join(lines)


def figures(table: Table, a: dict, out: Path) -> list[Path]:
    plt = pyplot()

    xs = a["xs"]
    paths = []
    for key, ylabel, fname, title in (
        (
            "twist_deg",
            "rod rotation Δα (deg)",
            "spiral_rotation.png",
            "Rod rotation relative to barrel (paper Fig. 5)",
        ),
        (
            "extension_mm",
            "passive extension Δl2 (mm)",
            "spiral_extension.png",
            "Passive spiral extension (paper Fig. 6)",
        ),
    ):
        fig, ax = plt.subplots(figsize=(6.4, 4.2))
        for leg in range(6):
            ax.plot(xs, a[key][:, leg], label=f"leg {leg + 1}", ls="-" if leg < 3 else "--")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel(ylabel)
        ax.set_title(f"{title}\n{table.name}", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(ncol=2, fontsize=8)
        fig.tight_layout()
        fig.savefig(out / fname, dpi=110)
        plt.close(fig)
        paths.append(out / fname)

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4))
    raw, comp = a["line_err_raw"], a["line_err_comp"]
    for c in range(3):
        a1.plot(xs, raw[:, c], label=f"{POSE_COLUMNS[c]}")
        a2.plot(xs, raw[:, c + 3] * ARCSEC_PER_RAD, label=f"about {POSE_COLUMNS[c]}")
    a1.plot(xs, np.linalg.norm(comp[:, :3], axis=1), "k:", label="|error|, compensated")
    a2.plot(
        xs, np.linalg.norm(comp[:, 3:], axis=1) * ARCSEC_PER_RAD, "k:", label="|error|, compensated"
    )
    a1.set_ylabel("translation error (mm)")
    a2.set_ylabel("rotation error (arcsec)")
    for ax in (a1, a2):
        ax.set_xlabel("commanded x (mm)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(
        f"Pose error from the passive spiral term along x, uncompensated ({table.name})",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(out / "spiral_pose_error.png", dpi=110)
    plt.close(fig)
    paths.append(out / "spiral_pose_error.png")
    return paths


def spiral_report(
    table: Table, out_dir, workspace: Workspace = Workspace(), n_random: int = 20000
) -> str:
    """Write spiral.md and three figures into `out_dir`; return the Markdown text."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    a = spiral_analysis(table, workspace, n_random)
    text = markdown(table, a, workspace)
    (out / "spiral.md").write_text(text)
    figures(table, a, out)
    return text
