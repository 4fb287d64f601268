"""Design trade studies for the reference table's workspace: the screw lead trade, radius
ratio × joint pair angle maps, the hand assignment that minimises the uncompensated spiral
error, and the cheapest tolerances that keep the ±0.2 mm target.

Run:  python studies/design_tradeoffs.py [--quick] [--out DIR]
      (writes design_tradeoffs.md and design_*.png into DIR, default results/)
"""

import argparse
import time
from pathlib import Path

import numpy as np

import jaxtable as jt

RESULTS = Path(__file__).resolve().parents[1] / "results"
LEADS = [5.0, 10.0, 12.7, 16.0, 20.0]
SOURCES = jt.Tolerances().sources
MAP_KEYS = [
    ("gci", "GCI (mean LCI)"),
    ("min_stiffness_translation_N_per_mm", "worst force stiffness (N/mm)"),
    ("max_position_sigma_mm", "worst RMS position σ (mm)"),
    ("first_frequency_Hz", "first natural frequency (Hz)"),
]


def lead_trade(design, poses):
    designs = []
    for lead in LEADS:
        tol = jt.Tolerances(**{**jt.Tolerances().as_dict(), "spiral_lead": 1e-3 * lead})
        designs.append(design.replace({"lead": lead, "tolerances.spiral_lead": tol.spiral_lead}))
    c = jt.assess_designs(jt.Design.stack(designs), poses)
    rows = [
        {
            "lead": lead,
            "spiral_mm": c["max_spiral_error_mm"][i],
            "sigma_mm": c["max_position_sigma_mm"][i],
            "rpm": c["max_motor_rpm"][i],
            "torque": c["max_motor_torque_Nm"][i],
        }
        for i, lead in enumerate(LEADS)
    ]
    return rows


def lead_figure(rows, path):
    plt = jt.reports.pyplot()
    lead = [r["lead"] for r in rows]
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    ax[0].plot(lead, [1e3 * r["spiral_mm"] for r in rows], "o-", label="uncompensated spiral")
    ax[0].plot(lead, [1e3 * r["sigma_mm"] for r in rows], "s-", label="budget σ (compensated)")
    ax[0].set_ylabel("worst position error (µm)")
    ax[0].legend()
    ax[1].plot(lead, [r["rpm"] for r in rows], "o-", color="C2", label="motor speed")
    ax[1].set_ylabel("worst motor speed (rpm)")
    tw = ax[1].twinx()
    tw.plot(lead, [r["torque"] for r in rows], "s-", color="C3", label="motor torque")
    tw.set_ylabel("worst motor torque (N·m)")
    for a in ax:
        a.set_xlabel("screw lead (mm/rev)")
        a.grid(alpha=0.3)
    fig.legend(loc="upper center", ncol=4, fontsize=8)
    fig.tight_layout(rect=(0, 0, 1, 0.92))
    fig.savefig(path, dpi=80)
    plt.close(fig)


def geometry_maps(design, poses, n):
    ratio = np.linspace(0.3, 0.8, n)
    angle = np.linspace(3.0, 25.0, n)
    R, A = np.meshgrid(ratio, angle, indexing="ij")
    base = float(design.geometry.base_radius)
    designs = [
        design.replace(
            {
                "platform_radius": r * base,
                "base_half_angle": np.radians(a),
                "platform_half_angle": np.radians(a),
            }
        )
        for r, a in zip(R.ravel(), A.ravel())
    ]
    t0 = time.perf_counter()
    c = jt.assess_designs(jt.Design.stack(designs), poses)
    seconds = time.perf_counter() - t0
    return ratio, angle, {k: v.reshape(n, n) for k, v in c.items()}, seconds


def maps_figure(ratio, angle, maps, ref, path):
    plt = jt.reports.pyplot()
    fig, axes = plt.subplots(2, 2, figsize=(11, 8.5))
    for ax, (key, title) in zip(axes.ravel(), MAP_KEYS):
        cs = ax.contourf(ratio, angle, maps[key].T, levels=16, cmap="viridis")
        fig.colorbar(cs, ax=ax)
        cov = maps["coverage"].T
        if cov.min() < 1:
            ax.contour(ratio, angle, cov, levels=[0.999], colors="w", linestyles="--")
        ax.plot(*ref, "r*", ms=14, label="reference")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("platform / base joint radius")
        ax.set_ylabel("joint pair half angle, base = platform (deg)")
    axes[0, 0].legend(loc="upper right")
    fig.suptitle("geometry trade (white dashes: full workspace coverage boundary)")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def rank(maps, key, value):
    """Fraction of the covering grid designs at least as good as `value`."""
    sense = jt.DESIGN_CRITERIA[key].sense
    ok = maps["coverage"] >= 1.0
    v = maps[key][ok]
    better = v >= value if sense == "max" else v <= value
    return float(np.mean(better))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="coarse maps and pose set (~2 min)")
    ap.add_argument("--out", type=Path, default=RESULTS, help="output folder (default results/)")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    table = jt.reference_table()
    design = jt.Design(jt.SymmetricDesign.from_table(table), jt.hardware_for(table))
    ws = jt.Workspace()
    poses = jt.design_poses(ws, n_sweep=7 if args.quick else 11, n_random=64 if args.quick else 256)
    ref = jt.assess_design(design, workspace=poses)
    hw = design.hardware
    lines = [
        "# Design trade studies: the reference table",
        "",
        f"Required workspace: {ws.describe()} ({len(poses)} poses). Motion specification: "
        f"{float(hw.moving_mass(table)):g} kg moving (payload {float(hw.payload):g} kg), "
        f"{float(hw.acceleration):g} m/s² and {float(hw.velocity):g} mm/s in any direction plus "
        f"{np.degrees(float(hw.angular_velocity)):g} °/s; legs {float(hw.leg_stiffness[0]):g} "
        f"N/mm; screw efficiency {float(hw.efficiency):g}. Tolerances: the paper's budget.",
        "",
        "## The reference design",
        "",
        "| criterion | value | unit |",
        "|---|---|---|",
    ]
    lines += [
        f"| `{k}` | {ref.values[k]:.4g} | {c.unit or '–'} |" for k, c in jt.DESIGN_CRITERIA.items()
    ]

    # ---- lead
    rows = lead_trade(design, poses)
    lead_figure(rows, args.out / "design_lead.png")
    r127 = next(r for r in rows if r["lead"] == 12.7)
    lines += [
        "",
        "## The lead trade",
        "",
        "Lead tolerance 0.1 % of the lead (the budget's `spiral_lead` scaled with it).",
        "",
        "| lead mm/rev | uncompensated spiral µm | budget σ µm (compensated) | motor rpm | "
        "torque N·m |",
        "|---|---|---|---|---|",
    ]
    lines += [
        f"| {r['lead']:g} | {1e3 * r['spiral_mm']:.0f} | {1e3 * r['sigma_mm']:.1f} | "
        f"{r['rpm']:.0f} | {r['torque']:.2f} |"
        for r in rows
    ]
    slope = np.polyfit([r["lead"] for r in rows], [r["spiral_mm"] for r in rows], 1)[0]
    sig = [r["sigma_mm"] for r in rows]
    lines += [
        "",
        f"The uncompensated spiral error grows {1e3 * slope:.0f} µm per mm/rev of lead "
        f"({1e3 * r127['spiral_mm']:.0f} µm at the reference 12.7 mm): "
        + (
            "above the ±0.2 mm target for every lead of the catalogue, so compensation is not "
            "optional."
            if all(r["spiral_mm"] > 0.2 for r in rows)
            else "within the ±0.2 mm target only for leads ≤ "
            f"{max(r['lead'] for r in rows if r['spiral_mm'] <= 0.2):g} mm/rev."
        )
        + " Compensated, the budget σ changes by "
        f"{1e3 * (max(sig) - min(sig)):.1f} µm over the catalogue: the lead no longer matters "
        "for accuracy. Speed and torque trade against each other as 1/lead and lead: "
        f"{rows[0]['rpm']:.0f} rpm / {rows[0]['torque']:.2f} N·m at {rows[0]['lead']:g} mm/rev, "
        f"{rows[-1]['rpm']:.0f} rpm / {rows[-1]['torque']:.2f} N·m at {rows[-1]['lead']:g}.",
        "",
        "![lead](design_lead.png)",
    ]

    # ---- geometry maps
    n = 9 if args.quick else 21
    ratio, angle, maps, seconds = geometry_maps(design, poses, n)
    ref_point = (
        float(design.geometry.platform_radius / design.geometry.base_radius),
        float(np.degrees(design.geometry.base_half_angle)),
    )
    maps_figure(ratio, angle, maps, ref_point, args.out / "design_geometry_maps.png")
    lines += [
        "",
        "## Radius ratio × joint pair angle",
        "",
        f"{n}×{n} designs (platform radius = ratio × {float(design.geometry.base_radius):g} mm, "
        f"both pair half angles equal), each over the {len(poses)} poses: "
        f"{n * n * len(poses):,} design-pose evaluations in one vmapped program, "
        f"{seconds:.1f} s ({n * n * len(poses) / seconds:,.0f} /s, compile included).",
        "",
        "| criterion | reference | best covering grid design | at (ratio, half angle) | "
        "grid designs at least as good as the reference |",
        "|---|---|---|---|---|",
    ]
    R, A = np.meshgrid(ratio, angle, indexing="ij")
    ok = maps["coverage"] >= 1.0
    best = {}
    for key, _ in MAP_KEYS + [("min_lci", "")]:
        sense = jt.DESIGN_CRITERIA[key].sense
        v = np.where(ok, maps[key], -np.inf if sense == "max" else np.inf)
        i = np.unravel_index(np.argmax(v) if sense == "max" else np.argmin(v), v.shape)
        best[key] = (maps[key][i], R[i], A[i])
        lines.append(
            f"| `{key}` | {ref.values[key]:.4g} | {maps[key][i]:.4g} | "
            f"({R[i]:.2f}, {A[i]:.0f}°) | {100 * rank(maps, key, ref.values[key]):.0f} % |"
        )
    lines += [
        "",
        f"{100 * ok.mean():.0f} % of the grid covers the whole workspace.",
        "",
        "![maps](design_geometry_maps.png)",
    ]
    ranks = {k: rank(maps, k, ref.values[k]) for k, _ in MAP_KEYS}

    # ---- hands
    hands = jt.optimize_design(design, ["hand"], "max_spiral_error_mm", workspace=poses)
    best_hand = np.asarray(hands.variables["hand"][1])
    hand_text = " ".join("R" if h > 0 else "L" for h in best_hand)
    others = [k for k in jt.DESIGN_CRITERIA if k != "max_spiral_error_mm"]
    rel = {
        k: abs(hands.optimum.values[k] - hands.start.values[k]) / (abs(hands.start.values[k]) or 1)
        for k in others
    }
    worst_other = max(rel, key=rel.get)
    # the table's symmetry makes several assignments equal: say so rather than name one
    n_tied = int(np.sum(hands.candidates <= hands.candidates.min() * (1 + 1e-6)))
    tied = f" (one of {n_tied} that tie to 1 ppm)" if n_tied > 1 else ""
    lines += [
        "",
        "## Hand per leg",
        "",
        f"All 64 assignments enumerated: legs 1-6 = {hand_text}{tied} gives the smallest "
        f"uncompensated spiral error, {1e3 * hands.value:.0f} µm against "
        f"{1e3 * hands.start_value:.0f} µm with six right-hand screws "
        f"({100 * (1 - hands.value / hands.start_value):.0f} % less; the 64 span "
        f"{1e3 * hands.candidates.min():.0f}-{1e3 * hands.candidates.max():.0f} µm). "
        f"Every other criterion moves by at most {100 * rel[worst_other]:.2g} % (`{worst_other}`,"
        " through the spiral's small share of the Jacobian): a screw's hand only flips the "
        "sign of its passive term. The cost is in the hardware (two screw and nut types to "
        "stock) and it does not remove the need to compensate: the best mix still leaves "
        f"{1e3 * hands.value:.0f} µm.",
    ]

    # ---- tolerances
    paper = jt.Tolerances()
    bounds = {f"tolerances.{s}": (0.1 * getattr(paper, s), 10 * getattr(paper, s)) for s in SOURCES}
    limit = 0.1
    alloc = jt.optimize_design(
        design,
        list(bounds),
        "tolerance_cost",
        [jt.parse_constraint(f"max_position_sigma_mm<={limit}")],
        workspace=poses,
        bounds=bounds,
        starts=3,
        progress=True,
    )
    lines += [
        "",
        "## Tolerance allocation",
        "",
        f"Cheapest tolerances (cost ∝ 1/tolerance, 1 per source at the paper's value) with the "
        f"worst RMS position σ ≤ {limit:g} mm, i.e. 2σ within the ±0.2 mm target everywhere in "
        "the workspace (spiral compensated). Found by gradient from 3 starts, bounds 0.1-10× the "
        "paper's values.",
        "",
        "| source | paper | allocated | unit |",
        "|---|---|---|---|",
    ]
    units = {
        "base_joints": "mm",
        "platform_joints": "mm",
        "zero_length": "mm",
        "lead_error": "mm / 300 mm",
        "clearance": "mm",
        "spiral_lead": "mm/rev",
    }
    for s in SOURCES:
        v0, v1 = alloc.variables[f"tolerances.{s}"]
        lines.append(f"| {s} | {v0:.4g} | {v1:.4g} | {units[s]} |")
    lines += [
        "",
        f"Cost {alloc.start_value:.2f} → {alloc.value:.2f} "
        f"({100 * (1 - alloc.value / alloc.start_value):.0f} % cheaper); worst σ "
        f"{alloc.start.values['max_position_sigma_mm']:.4f} → "
        f"{alloc.optimum.values['max_position_sigma_mm']:.4f} mm "
        f"({'met' if alloc.feasible else 'NOT met'}).",
    ]
    loosest = max(SOURCES, key=lambda s: alloc.variables[f"tolerances.{s}"][1] / getattr(paper, s))
    tightest = min(SOURCES, key=lambda s: alloc.variables[f"tolerances.{s}"][1] / getattr(paper, s))

    # ---- conclusions
    conclusions = [
        f"- Lead: compensation is required for any catalogue lead (uncompensated "
        f"{1e3 * rows[0]['spiral_mm']:.0f}-{1e3 * rows[-1]['spiral_mm']:.0f} µm); with it the "
        f"lead is a speed/torque choice only.",
        f"- Geometry: the reference is in the best {100 * max(ranks.values()):.0f} % of the "
        "covering grid designs on every mapped criterion, not at the optimum: "
        + "; ".join(
            f"`{k}` {ref.values[k]:.4g} → {best[k][0]:.4g} "
            f"({100 * abs(best[k][0] / ref.values[k] - 1):.0f} % better, at ratio "
            f"{best[k][1]:.2f}, {best[k][2]:.0f}°)"
            for k, _ in MAP_KEYS
        )
        + "."
        + (
            f" Every best point has a smaller pair angle than the reference's {ref_point[1]:.0f}°."
            if all(best[k][2] < ref_point[1] for k, _ in MAP_KEYS)
            else ""
        ),
        f"- Hands: {hand_text}{tied} cuts the uncompensated spiral error by "
        f"{100 * (1 - hands.value / hands.start_value):.0f} %; other criteria move by "
        f"{100 * rel[worst_other]:.2g} % at most.",
        f"- Tolerances: the target holds at {100 * alloc.value / alloc.start_value:.0f} % of the "
        f"paper budget's cost; the allocation loosens `{loosest}` most (to its bound: its "
        f"share of σ is negligible) and tightens `{tightest}` most, the source that dominates "
        "the budget.",
    ]
    lines += ["", "## Conclusions", "", *conclusions]
    lines += [
        "",
        f"Run time {time.perf_counter() - t0:.0f} s (`python studies/design_tradeoffs.py"
        + (" --quick" if args.quick else "")
        + "`).",
    ]
    (args.out / "design_tradeoffs.md").write_text("\n".join(lines) + "\n")
    print("\n".join(conclusions))
    print(f"\nwrote {args.out / 'design_tradeoffs.md'} in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
