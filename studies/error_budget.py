"""Error budget of the reference table: the paper's tolerances propagated over the workspace.

- linear propagation (autodiff sensitivities, the paper's eq. (11) generalised) over slices and
  over the whole workspace (each DOF alone + the combined box), per source and in total,
  with the passive spiral term compensated or not, against the ±0.2 mm design target;
- Monte Carlo through the exact forward kinematics to check the linear picture, and where it
  breaks down;
- with --big, a 10⁷-pose map with its time and peak memory.

Run:  python studies/error_budget.py [--big]      (writes results/error_budget*.{md,png})
"""

import argparse
import resource
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np

import jaxtable as jt
from jaxtable._errormap import PoseList, budget_one, error_map, workspace_slice
from jaxtable._map_report import budget_chart, slice_figures, summary_markdown, x_stroke_figure
from jaxtable._montecarlo import monte_carlo
from jaxtable._tolerance import SOURCES, Tolerances

OUT = Path(__file__).resolve().parents[1] / "results"
SLICES = [(("x", "y"), None), (("roll", "pitch"), None), (("z", "yaw"), None)]


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def mc_table(table, tol):
    sig = tuple(tol.sigma(s) for s in SOURCES)
    cases = [
        ("home", [0, 0, 0, 0, 0, 0], 1),
        ("x = -200 mm", [-200, 0, 0, 0, 0, 0], 1),
        ("box corner", [100, -100, -50, -7.5, -7.5, 10], 1),
        ("box corner, tolerances x100", [100, -100, -50, -7.5, -7.5, 10], 100),
        ("z = -600 mm (legs 13 deg from flat)", [0, 0, -600, 0, 0, 0], 1),
        ("z = -652 mm (platform 10 mm above base)", [0, 0, -652, 0, 0, 0], 1),
        ("z = -655 mm", [0, 0, -655, 0, 0, 0], 1),
    ]
    lines = [
        "| pose | tolerances | cond | σ_z linear (mm) | σ_z MC / linear | RMS_z MC / linear "
        "| mean_z MC / σ_z | σ_roll MC / linear | no solution |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    n = 4000
    for name, p, f in cases:
        pose = jt.Workspace.to_internal(np.array(p, float))
        std, _, cond, _ = budget_one(table, tuple(f * s for s in sig), jnp.asarray(pose))
        lin = np.asarray(std[-1])
        err = monte_carlo(table, pose[None], tol.scaled(f), n, seed=7, allow_failures=True)[:, 0]
        ok = ~np.isnan(err[:, 0])
        e = err[ok]
        lines.append(
            f"| {name} | x{f} | {float(cond):.1f} | {lin[2]:.4f} | {e[:, 2].std() / lin[2]:.3f} "
            f"| {np.sqrt((e[:, 2] ** 2).mean()) / lin[2]:.3f} | {e[:, 2].mean() / lin[2]:+.3f} "
            f"| {e[:, 3].std() / lin[3]:.3f} | {100 * (1 - ok.mean()):.1f} % |"
        )
    return "\n".join(lines), n


def big_map(table, tol, n_side=3163):
    small = workspace_slice(("x", "y"), 64)
    error_map(table, tol, small, keep=False)  # compile first
    before = peak_rss_mib()
    grid = workspace_slice(("x", "y"), n_side)
    t0 = time.perf_counter()
    _, summary = error_map(table, tol, grid, keep=False, progress=True)
    dt = time.perf_counter() - t0
    return summary, dt, before, peak_rss_mib()


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--big", action="store_true", help="also run the 10^7-pose map (~3 min)")
    args = ap.parse_args()
    OUT.mkdir(exist_ok=True)
    table = jt.reference_table()
    tol = Tolerances()
    md = [
        "# Error budget: reference table, the paper's tolerances",
        "",
        "`python studies/error_budget.py` — linear propagation by autodiff (first order in "
        "the tolerances), Monte Carlo through the exact forward kinematics as a check. "
        "Rotation errors are rotation-vector angles. Tolerances (1σ; clearance = w, acting as "
        "±w/2): " + ", ".join(f"{k} = {v:g}" for k, v in tol.as_dict().items()) + " (mm, mm/rev).",
        "",
    ]
    ws = jt.Workspace()
    poses = np.concatenate([*ws.sweeps(81), ws.box_samples(50000)])
    _, summary = error_map(table, tol, PoseList(poses), keep=False, progress=True)
    md.append(summary_markdown(summary, f"Whole workspace ({ws.describe()})"))
    budget_chart(summary, OUT, "error_budget")
    S = summary["sources"]
    joint = S["base_joints"]["trans_max_mm"]
    md += [
        "### Does leg-length error dominate the 10 µm joint errors (the paper's claim)?",
        "",
        f"Largest RMS translation error per source: joints {joint:.4f} mm (each of base and "
        f"platform; to first order a joint error δ moves its leg by u·δ, so 10 µm per "
        f"coordinate acts like a 10 µm leg-length error), lead error "
        f"{S['lead_error']['trans_max_mm']:.4f} mm (zero at home, growing with travel), "
        f"clearance {S['clearance']['trans_max_mm']:.4f} mm, and the uncompensated passive "
        f"spiral bias brings the total to {S['total (spiral uncompensated)']['trans_max_mm']:.3f}"
        f" mm against {S['total']['trans_max_mm']:.4f} mm compensated. Confirmed for the "
        f"clearance ({S['clearance']['trans_max_mm'] / joint:.1f}x a joint source) and for the "
        f"passive spiral term when it is not compensated; the lead error is only comparable "
        f"with the joint errors ({S['lead_error']['trans_max_mm'] / joint:.2f}x at its worst).",
        "",
    ]
    for dofs, fixed in SLICES:
        grid = workspace_slice(dofs, 81, fixed=fixed)
        emap, s = error_map(table, tol, grid)
        slice_figures(table, emap, OUT, f"error_map_{dofs[0]}_{dofs[1]}")
        md.append(summary_markdown(s, f"{dofs[0]}-{dofs[1]} slice (81 x 81), the rest at home"))
    x_stroke_figure(table, tol, OUT)
    mc, n = mc_table(table, tol)
    md += [
        "### Linear propagation against Monte Carlo",
        "",
        f"{n} hardware realisations per row, exact forward kinematics (Newton, spiral inside) "
        "from the nominal compensated command. Standard error of an estimated σ ≈ 1.1 %, of a "
        "mean ≈ 1.6 % of σ.",
        "",
        mc,
        "",
        "Inside the workspace the linear picture holds to the Monte Carlo noise even at 100x "
        "the paper's tolerances: the hexapod is well conditioned there (condition number <= "
        f"{summary['cond_max']:.1f}). It breaks down near the singular low pose, where the legs "
        "lie almost flat: the z error becomes skewed (mean off zero, RMS above the linear σ) and, "
        "lower still, some realisations have no pose near the command at all, which no "
        "covariance can express.",
        "",
        "Figures: error_budget.png (per-source bars), error_x_stroke.png (paper Fig. 9 axis), "
        "error_map_*.png (slices: σ, spiral bias, condition number, dominant source).",
        "",
    ]
    if args.big:
        s, dt, before, after = big_map(table, tol)
        big = [
            "# A 10^7-pose error map",
            "",
            f"x-y slice of 3163 x 3163 = {s['poses']} poses, per-pose sensitivities to 54 "
            f"parameters, chunks of 8192: {dt:.1f} s ({s['poses'] / dt:,.0f} poses/s), "
            f"peak resident memory {after:.0f} MiB (process before the map: {before:.0f} MiB; "
            f"the map added {after - before:.0f} MiB). Largest total translation σ "
            f"{s['sources']['total']['trans_max_mm']:.4f} mm.",
            "",
            "`python studies/error_budget.py --big`",
            "",
        ]
        (OUT / "error_budget_big.md").write_text("\n".join(big))
        print("\n".join(big))
    (OUT / "error_budget.md").write_text("\n".join(md))
    print("\n".join(md))


if __name__ == "__main__":
    main()
