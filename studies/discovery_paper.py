"""The paper's story re-enacted with `jaxtable diagnose` on the reference table.

1. The hardware has the passive spiral term; the controller commands the rigid inverse
   kinematics (as before the paper's compensation). Two experiments: the paper's x-line
   laser interferometer (x every 25 mm, x column only) and a 6-D tracker over the workspace.
   Diagnose both from the rigid model; report what is named, the screw lead and hand
   recovered, and the gain.
2. With the spiral compensated, a residual trend linear in x of ±0.1 mm (the paper's Fig. 9):
   which parameters could cause it, and which of them an x-only interferometer on the x line
   can tell apart (identification Jacobian, singular vectors).

Run:  python studies/discovery_paper.py      (writes results/discovery_paper.md + PNGs)
"""

from pathlib import Path

import numpy as np

import jaxtable as jt
from jaxtable._calibrate import fit, setup
from jaxtable._diagnose import GEOMETRY, diagnose
from jaxtable._diagnose_report import effect_figures
from jaxtable._instrument import interferometer, tracker6
from jaxtable._map_report import _plt
from jaxtable._simulate import perturb_table, plan_random, plan_x_line, simulate

OUT = Path(__file__).resolve().parents[1] / "results"


def quiet(_):
    pass


def part1(nominal, true, lines):
    spiral = {"spiral": jt.Spiral.from_table(nominal)}
    runs = {
        "x-line interferometer (17 stops, x only)": simulate(
            nominal, true, plan_x_line(), interferometer(), effects=spiral, compensate=False
        ),
        "6-D tracker, 150 random stops": simulate(
            nominal,
            true,
            plan_random(150, 1),
            tracker6(),
            effects=spiral,
            compensate=False,
            frame=[900.0, 200.0, 100.0, 0.0, 0.0, np.deg2rad(15.0)],
            seed=1,
        ),
    }
    lines += [
        "## 1. The rigid model against data from a table with the passive spiral term",
        "",
        "| experiment | selected | unexplained | RMS before → after (σ) | held-out RMS "
        "before → after (σ) |",
        "|---|---|---|---|---|",
    ]
    diags = {}
    for name, data in runs.items():
        d = diagnose(data, nominal, log=quiet)
        diags[name] = d
        lines.append(
            f"| {name} | {', '.join(d.selected) or 'none'} | {d.unexplained} | "
            f"{d.rms_before:.2f} → {d.rms_after:.2f} | "
            f"{d.heldout_rms_before:.2f} → {d.heldout_rms_after:.2f} |"
        )
    lines.append("")
    x_run = diags["x-line interferometer (17 stops, x only)"]
    t_run = diags["6-D tracker, 150 random stops"]
    lines += [
        f"- The x-line interferometer sees nothing: x RMS of the rigid fit "
        f"{1e3 * x_run.base.rms_after['x']:.2f} µm at 1 µm noise. Along x the passive term "
        "moves the platform sideways and rolls it (results/spiral.md), and the little it "
        "changes x is absorbed by the geometry the fit can still move; the data are "
        "consistent with the rigid model. This is why the paper needed its analysis rather "
        "than its x measurement to find the term.",
    ]
    if "spiral" in t_run.selected:
        v, s = t_run.effect_params("spiral")["lead"]
        lead = np.abs(v)
        hand = ["right" if x > 0 else "left" for x in v]
        w = 1 / s**2
        mean = float((lead * w).sum() / w.sum())
        lines += [
            f"- The 6-D tracker names the spiral term first (ΔBIC "
            f"{t_run.candidates[0].delta_bic:.0f}); per-leg signed lead recovered as "
            + ", ".join(f"{a:+.3f}±{b:.3f}" for a, b in zip(v, s))
            + f" mm/rev: hand {set(hand)}, weighted mean lead {mean:.4f} mm/rev "
            f"(hardware {float(nominal.lead[0])} mm/rev, right hand).",
            f"- Gain: RMS {t_run.rms_before:.2f} → {t_run.rms_after:.2f} σ, held-out "
            f"{t_run.heldout_rms_before:.2f} → {t_run.heldout_rms_after:.2f} σ; per column "
            + ", ".join(
                f"{c} {t_run.base.rms_after[c] * (1e3 if k < 3 else 206264.8):.1f} → "
                f"{t_run.final.rms_after[c] * (1e3 if k < 3 else 206264.8):.1f}"
                for k, c in enumerate(t_run.final.rms_after)
            )
            + " (µm / arcsec).",
        ]
    figs = effect_figures(t_run, OUT)
    renamed = []
    for p in figs:
        q = p.with_name("discovery_" + p.name)
        p.replace(q)
        renamed.append(q)
    lines += [""] + [f"![{p.stem}]({p.name})" for p in renamed] + [""]


def part2(nominal, true, lines):
    """A linear-in-x trend with the spiral compensated: who could cause it."""
    eps = 6.0e-4  # lead_scale on every leg; gives about ±0.1 mm along the x stroke
    eff = {"spiral": jt.Spiral.from_table(nominal), "lead_scale": jt.LeadScale(eps)}
    plan = plan_x_line()
    data = simulate(nominal, true, plan, interferometer(), effects=eff, compensate=True)
    clean = simulate(
        nominal, true, plan, interferometer(), effects={"spiral": eff["spiral"]}, compensate=True
    )
    trend = data.measured[:, 0] - clean.measured[:, 0]
    slope = np.polyfit(plan[:, 0], trend, 1)[0]
    # identification Jacobian of the x readings: geometry + lead_scale + interferometer offset
    free = GEOMETRY + ("lead_scale.eps",)
    effects = {"spiral": jt.Spiral.from_table(nominal), "lead_scale": jt.LeadScale(0.0)}
    st = setup(nominal, data, free, effects=effects, compensated=True)
    cal = fit(st)
    J = cal.jacobian[np.isfinite(data.measured).reshape(-1)]
    names = cal.names
    # how well each parameter group alone reproduces the trend (least squares on J columns)
    target = trend / 0.001  # the trend in σ units (the interferometer's 1 µm)

    def explain(cols):
        A = J[:, cols]
        coef, *_ = np.linalg.lstsq(A, target, rcond=None)
        return 1 - np.sum((A @ coef - target) ** 2) / np.sum(target**2)

    groups = {
        "lead_scale ε (6)": [i for i, n in enumerate(names) if n.startswith("lead_scale")],
        "zero_lengths L0 (6)": [i for i, n in enumerate(names) if n.startswith("zero_lengths")],
        "base joints b_i (18)": [i for i, n in enumerate(names) if n.startswith("base_joints")],
        "platform joints a_i (18)": [
            i for i, n in enumerate(names) if n.startswith("platform_joints")
        ],
    }
    rank = int(np.sum(cal.singular_values > 1e-6))
    d = diagnose(data, nominal, compensated=True, base=("spiral",), log=quiet)
    lines += [
        "## 2. Spiral compensated, a residual trend linear in x (the paper's Fig. 9)",
        "",
        f"Simulated: the hardware's screws run {eps:.1e} long (lead_scale on every leg), the "
        f"controller compensates the spiral term; along the x line the interferometer sees a "
        f"trend of {1e3 * slope * 200:+.1f} µm at x = +200 mm ({1e3 * np.ptp(trend):.0f} µm "
        "peak to peak), linear in x like the paper's.",
        "",
        f"The x-line interferometer gives {len(plan)} numbers; the 42 geometric parameters + "
        f"6 lead scales + the interferometer's offset are {len(names)} unknowns, of which its "
        f"data determine {rank} combinations. Share of the trend each group alone can "
        "reproduce:",
        "",
        "| parameter group | share of the trend explained |",
        "|---|---|",
    ]
    for g, cols in groups.items():
        lines.append(f"| {g} | {100 * explain(cols):.1f} % |")
    lines += [
        "",
        "A lead error, a leg-zero error pattern and the joint radii all produce the same "
        "straight line in x: from this experiment the cause cannot be named, only the "
        "combination corrected. `jaxtable diagnose` on these data (spiral in the base model) "
        f"selects {d.selected or 'nothing'} and reports unexplained = {d.unexplained}: the "
        "geometric fit absorbs the trend (RMS "
        f"{1e3 * d.base.rms_before['x']:.1f} → {1e3 * d.base.rms_after['x']:.2f} µm in x). "
        "Telling them apart needs poses where their signatures differ: the 6-D tracker run "
        "below names the lead error.",
        "",
    ]
    data6 = simulate(
        nominal, true, plan_random(150, 3), tracker6(), effects=eff, compensate=True, seed=3
    )
    d6 = diagnose(data6, nominal, compensated=True, base=("spiral",), log=quiet)
    v, s = d6.effect_params("lead_scale")["eps"] if "lead_scale" in d6.selected else ([], [])
    lines += [
        f"6-D tracker, 150 stops, same hardware: selected {d6.selected}, unexplained "
        f"{d6.unexplained}; ε per leg "
        + ", ".join(f"{1e4 * a:.3f}±{1e4 * b:.3f}e-4" for a, b in zip(v, s))
        + f" (true {1e4 * eps:.1f}e-4).",
        "",
    ]
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 3.5))
    ax.plot(plan[:, 0], 1e3 * trend, "o-", label="lead error 6e-4 (simulated)")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("x error (µm)")
    ax.axhline(0, color="k", lw=0.5)
    ax.set_title("Spiral compensated: x error along the x line (cf. the paper's Fig. 9)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(OUT / "discovery_fig9_trend.png", dpi=110)
    plt.close(fig)
    lines += ["![trend](discovery_fig9_trend.png)", ""]


if __name__ == "__main__":
    OUT.mkdir(exist_ok=True)
    nominal = jt.reference_table()
    true = perturb_table(nominal, 7, joint_sigma=0.010, zero_sigma=0.050)
    lines = [
        "# The paper's story with `jaxtable diagnose` (reference table, simulated)",
        "",
        "Hardware: the reference table with random geometric errors (joints σ 10 µm, L0 σ "
        "50 µm), right-hand screws of 12.7 mm lead. Regenerate: "
        "`python studies/discovery_paper.py`.",
        "",
    ]
    part1(nominal, true, lines)
    part2(nominal, true, lines)
    text = "\n".join(lines)
    (OUT / "discovery_paper.md").write_text(text)
    print(text)
