"""The paper's story re-enacted with `jaxtable diagnose` on the reference table.

1. The hardware has the passive spiral term; the controller commands the rigid inverse
   kinematics (as before the paper's compensation). Two experiments: the paper's x-line
   laser interferometer (x every 25 mm, x column only) and a 6-D tracker over the workspace.
   Diagnose both from the rigid model; report what is named, the screw lead and hand
   recovered, and the gain.
2. With the spiral compensated, a residual trend linear in x of ±0.1 mm (the paper's Fig. 9):
   which parameters could cause it, and which of them an x-only interferometer on the x line
   can tell apart (identification Jacobian, singular vectors).

Run:  python studies/discovery_paper.py [--quick] [--out DIR]
      (writes discovery_paper.md, discovery_effect_*.png and discovery_fig9_trend.png into
      DIR, default results/)
"""

import argparse
import time
from pathlib import Path

import numpy as np

import jaxtable as jt

RESULTS = Path(__file__).resolve().parents[1] / "results"
ARCSEC = 180 * 3600 / np.pi
COLS = ("x", "y", "z", "roll", "pitch", "yaw")
# library: the candidate effects diagnose tries (None: all of jaxtable.EFFECTS); the quick run
# keeps the two this story is about
FULL = {"x_step": 25.0, "stops": 150, "folds": 5, "library": None}
QUICK = {"x_step": 25.0, "stops": 30, "folds": 3, "library": ("spiral", "lead_scale")}


def quiet(_):
    pass


def at_noise(rms_mm: float, noise_mm: float) -> bool:
    """A fit's residual RMS counts as 'at the noise' within 1.5x the instrument's σ."""
    return rms_mm < 1.5 * noise_mm


def spiral_along_x(nominal, line):
    """Largest |pose error| per column (µm / arcsec) along `line` when the controller does
    not compensate the passive term (exact forward kinematics, spiral inside)."""
    cmd = jt.actuator_command(nominal, line, compensated=False)
    err = np.asarray(jt.pose_error(np.asarray(jt.forward(nominal, cmd)), line))
    return np.abs(err).max(axis=0) * np.array([1e3] * 3 + [ARCSEC] * 3)


def part1(nominal, true, lines, size, out):
    spiral = {"spiral": jt.Spiral.from_table(nominal)}
    line = jt.plan_x_line(size["x_step"])
    interferometer = jt.interferometer()
    x_name = f"x-line interferometer ({len(line)} stops, x only)"
    t_name = f"6-D tracker, {size['stops']} random stops"
    runs = {
        x_name: jt.simulate(nominal, true, line, interferometer, effects=spiral, compensated=False),
        t_name: jt.simulate(
            nominal,
            true,
            jt.plan_random(size["stops"], 1),
            jt.tracker6(),
            effects=spiral,
            compensated=False,
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
        d = jt.diagnose(nominal, data, folds=size["folds"], library=size["library"], log=quiet)
        diags[name] = d
        lines.append(
            f"| {name} | {', '.join(d.selected) or 'none'} | {d.unexplained} | "
            f"{d.rms_sigma_before:.2f} → {d.rms_sigma_after:.2f} | "
            f"{d.heldout_rms_before:.2f} → {d.heldout_rms_after:.2f} |"
        )
    lines.append("")
    x_run, t_run = diags[x_name], diags[t_name]
    noise = interferometer.noise[0]
    x_rms = x_run.base.rms_columns_after["x"]
    move = spiral_along_x(nominal, line)
    trans = int(np.argmax(move[:3]))
    rot = 3 + int(np.argmax(move[3:]))
    effect = (
        f"along x the passive term (uncompensated, exact forward kinematics) moves the "
        f"platform by up to {move[0]:.1f} µm in x, {move[1]:.1f} µm in y, {move[2]:.1f} µm in "
        f"z and turns it by up to {move[3]:.0f}″ in roll, {move[4]:.0f}″ in pitch, "
        f"{move[5]:.0f}″ in yaw: mostly {COLS[trans]} and {COLS[rot]}"
        + (", hardly x" if move[0] < 0.1 * move[trans] else "")
    )
    if not x_run.selected and not x_run.unexplained:
        lines.append(
            f"- The x-line interferometer names nothing and flags nothing: x RMS of the rigid "
            f"fit {1e3 * x_rms:.2f} µm at {1e3 * noise:g} µm noise"
            + (" (at the noise)" if at_noise(x_rms, noise) else " (above the noise)")
            + f". Why: {effect}"
            + (
                "; the little it changes x is absorbed by the geometry the fit can still move, "
                "and the data are consistent with the rigid model. This is why the paper "
                "needed its analysis rather than its x measurement to find the term."
                if at_noise(x_rms, noise)
                else "."
            )
        )
    else:
        lines.append(
            f"- The x-line interferometer selects {x_run.selected or 'nothing'} (unexplained = "
            f"{x_run.unexplained}); x RMS of the rigid fit {1e3 * x_rms:.2f} µm at "
            f"{1e3 * noise:g} µm noise. For reference, {effect}."
        )
    if "spiral" in t_run.selected:
        v, s = t_run.effect_params("spiral")["lead"]
        lead = np.abs(v)
        hand = {"right" if x > 0 else "left" for x in v}
        hw_lead = np.asarray(nominal.lead, float)
        hw_hand = {"right" if h > 0 else "left" for h in np.asarray(nominal.hand)}
        w = 1 / s**2
        mean = float((lead * w).sum() / w.sum())
        se = float(1 / np.sqrt(w.sum()))
        z = (mean - float(hw_lead.mean())) / se
        ranked = [c.as_json()["effect"] for c in t_run.candidates]  # effect names, any form
        first = bool(ranked) and ranked[0] == "spiral"
        rank = ranked.index("spiral") + 1 if "spiral" in ranked else "?"
        lines += [
            "- The 6-D tracker "
            + (
                f"names the spiral term first (ΔBIC {t_run.candidates[0].delta_bic:.0f})"
                if first
                else f"selects the spiral term (ranked {rank} in the first step)"
            )
            + (
                "; one signed lead for all legs (the shared form) recovered as "
                if len(v) == 1
                else "; per-leg signed lead recovered as "
            )
            + ", ".join(f"{a:+.3f}±{b:.3f}" for a, b in zip(v, s))
            + f" mm/rev: hand {hand}, weighted mean lead {mean:.4f} ± {se:.4f} mm/rev "
            f"(hardware {hw_lead.mean():g} mm/rev, {'/'.join(sorted(hw_hand))} hand: hand "
            f"{'recovered' if hand == hw_hand else 'NOT recovered'}, mean lead "
            f"{abs(z):.1f} σ from the hardware's).",
            f"- Gain: RMS {t_run.rms_sigma_before:.2f} → {t_run.rms_sigma_after:.2f} σ, held-out "
            f"{t_run.heldout_rms_before:.2f} → {t_run.heldout_rms_after:.2f} σ; per column "
            + ", ".join(
                f"{c} {t_run.rms_columns_before[c] * (1e3 if k < 3 else ARCSEC):.1f} → "
                f"{t_run.rms_columns_after[c] * (1e3 if k < 3 else ARCSEC):.1f}"
                for k, c in enumerate(t_run.rms_columns_after)
            )
            + " (µm / arcsec).",
        ]
    else:
        lines.append(
            f"- The 6-D tracker does not select the spiral term: selected "
            f"{t_run.selected or 'nothing'}, unexplained = {t_run.unexplained}."
        )
    figs = jt.reports.effect_figures(t_run, out)
    renamed = []
    for p in figs:
        q = p.with_name("discovery_" + p.name)
        p.replace(q)
        renamed.append(q)
    lines += [""] + [f"![{p.stem}]({p.name})" for p in renamed] + [""]


def part2(nominal, true, lines, size, out):
    """A linear-in-x trend with the spiral compensated: who could cause it."""
    eps = 6.0e-4  # lead_scale on every leg; gives about ±0.1 mm along the x stroke
    eff = {"spiral": jt.Spiral.from_table(nominal), "lead_scale": jt.LeadScale(eps)}
    plan = jt.plan_x_line(size["x_step"])
    interferometer = jt.interferometer()
    noise = interferometer.noise[0]
    data = jt.simulate(nominal, true, plan, interferometer, effects=eff, compensated=True)
    clean = jt.simulate(
        nominal, true, plan, interferometer, effects={"spiral": eff["spiral"]}, compensated=True
    )
    trend = data.measured[:, 0] - clean.measured[:, 0]
    slope, icpt = np.polyfit(plan[:, 0], trend, 1)
    r2 = 1 - np.sum((trend - (slope * plan[:, 0] + icpt)) ** 2) / np.sum(
        (trend - trend.mean()) ** 2
    )
    # identification Jacobian of the x readings: geometry + lead_scale + interferometer offset
    free = jt.GEOMETRY + ("lead_scale.eps",)
    effects = {"spiral": jt.Spiral.from_table(nominal), "lead_scale": jt.LeadScale(0.0)}
    st = jt.setup(nominal, data, free, effects=effects, compensated=True)
    cal = jt.fit(st)
    J = cal.jacobian[np.isfinite(data.measured).reshape(-1)]
    names = cal.names
    # how well each parameter group alone reproduces the trend (least squares on J columns)
    target = trend / noise  # the trend in σ units

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
    shares = {g: explain(cols) for g, cols in groups.items()}
    n_geo = sum(n.startswith(jt.GEOMETRY) for n in names)
    n_lead = sum(n.startswith("lead_scale") for n in names)
    nuisance = [n for n in names if not n.startswith(jt.GEOMETRY + ("lead_scale",))]
    rank = int(np.sum(cal.singular_values > 1e-6))
    d = jt.diagnose(
        nominal,
        data,
        compensated=True,
        base=("spiral",),
        folds=size["folds"],
        library=size["library"],
        log=quiet,
    )
    lines += [
        "## 2. Spiral compensated, a residual trend linear in x (the paper's Fig. 9)",
        "",
        f"Simulated: the hardware's screws run {eps:.1e} long (lead_scale on every leg), the "
        f"controller compensates the spiral term; along the x line the interferometer sees a "
        f"trend of {1e3 * slope * 200:+.1f} µm at x = +200 mm ({1e3 * np.ptp(trend):.0f} µm "
        f"peak to peak), "
        + (
            f"linear in x like the paper's (R² of a straight line {r2:.4f})."
            if r2 > 0.99
            else f"not a straight line (R² {r2:.3f}), unlike the paper's."
        ),
        "",
        f"The x-line interferometer gives {len(plan)} numbers; the {n_geo} geometric "
        f"parameters + {n_lead} lead scales + the interferometer's frame "
        f"({', '.join(nuisance) or 'none'}) are {len(names)} unknowns, of which its data "
        f"determine {rank} combinations. Share of the trend each group alone can reproduce:",
        "",
        "| parameter group | share of the trend explained |",
        "|---|---|",
    ]
    for g, v in shares.items():
        lines.append(f"| {g} | {100 * v:.1f} % |")
    full = [g.split(" (")[0] for g, v in shares.items() if v >= 0.99]
    part = [g.split(" (")[0] for g, v in shares.items() if v < 0.99]
    x_before = d.base.rms_columns_before["x"]
    x_after = d.base.rms_columns_after["x"]
    lines += [""]
    if len(full) >= 2:
        lines.append(
            f"{', '.join(full)} each reproduce the straight line in x (≥ 99 %)"
            + (f"; {', '.join(part)} do not" if part else "")
            + ": from this experiment the cause cannot be named, only the combination "
            "corrected."
        )
    else:
        lines.append(
            f"Only {', '.join(full) or 'no group'} reproduces the trend (≥ 99 %): this "
            "experiment can tell the groups apart."
        )
    absorbed = at_noise(x_after, noise)
    lines += [
        "",
        f"`jaxtable diagnose` on these data (spiral in the base model) selects "
        f"{d.selected or 'nothing'}"
        + (
            " (a choice these data cannot support: the groups above reproduce the trend "
            "equally well)"
            if d.selected and len(full) >= 2
            else ""
        )
        + f" and reports unexplained = {d.unexplained}; the geometric "
        f"fit {'absorbs' if absorbed else 'does not absorb'} the trend (RMS "
        f"{1e3 * x_before:.1f} → {1e3 * x_after:.2f} µm in x, noise {1e3 * noise:g} µm). "
        "Telling the causes apart needs poses where their signatures differ: the 6-D tracker "
        "run below.",
        "",
    ]
    data6 = jt.simulate(
        nominal,
        true,
        jt.plan_random(size["stops"], 3),
        jt.tracker6(),
        effects=eff,
        compensated=True,
        seed=3,
    )
    d6 = jt.diagnose(
        nominal,
        data6,
        compensated=True,
        base=("spiral",),
        folds=size["folds"],
        library=size["library"],
        log=quiet,
    )
    if "lead_scale" in d6.selected:
        v, s = d6.effect_params("lead_scale")["eps"]
        within = int(np.sum(np.abs(v - eps) <= 3 * s))
        tail = (
            "; ε per leg "
            + ", ".join(f"{1e4 * a:.3f}±{1e4 * b:.3f}e-4" for a, b in zip(v, s))
            + f" (true {1e4 * eps:.1f}e-4; {within} of {len(v)} legs within 3σ of it). It "
            "names the lead error."
        )
    else:
        tail = ": it does not name the lead error either."
    lines += [
        f"6-D tracker, {size['stops']} stops, same hardware: selected {d6.selected}, "
        f"unexplained {d6.unexplained}" + tail,
        "",
    ]
    plt = jt.reports.pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 3.5))
    ax.plot(plan[:, 0], 1e3 * trend, "o-", label=f"lead error {eps:.0e} (simulated)")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("x error (µm)")
    ax.axhline(0, color="k", lw=0.5)
    ax.set_title("Spiral compensated: x error along the x line (cf. the paper's Fig. 9)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "discovery_fig9_trend.png", dpi=110)
    plt.close(fig)
    lines += ["![trend](discovery_fig9_trend.png)", ""]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer stops and cross-validation folds")
    ap.add_argument("--out", type=Path, default=RESULTS, help="output folder (default results/)")
    args = ap.parse_args(argv)
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    size = QUICK if args.quick else FULL
    nominal = jt.reference_table()
    true = jt.perturb_table(nominal, 7, joint_sigma=0.010, zero_sigma=0.050)
    hand = {"right" if h > 0 else "left" for h in np.asarray(nominal.hand)}
    leads = sorted({float(x) for x in np.asarray(nominal.lead)})
    lines = [
        "# The paper's story with `jaxtable diagnose` (reference table, simulated)",
        "",
        "Hardware: the reference table with random geometric errors (joints σ 10 µm, L0 σ "
        f"50 µm), {'/'.join(sorted(hand))}-hand screws of {', '.join(f'{x:g}' for x in leads)} "
        "mm lead. Candidate effects for `diagnose`: "
        + (
            "all of `jaxtable.EFFECTS` that apply to the data"
            if size["library"] is None
            else ", ".join(size["library"]) + " only (quick run)"
        )
        + ". Regenerate: "
        f"`python studies/discovery_paper.py{' --quick' if args.quick else ''}`.",
        "",
    ]
    part1(nominal, true, lines, size, out)
    part2(nominal, true, lines, size, out)
    text = "\n".join(lines)
    (out / "discovery_paper.md").write_text(text)
    print(text)
    print(f"total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
