"""Discovery power: how large must an effect be for `jaxtable diagnose` to name it?

For every library effect and every dictionary family, planted one at a time in runs of the
reference table: the probability that diagnose's first round names it (the first name is what
was planted), against its amplitude (peak reading change in units of the reading's σ), at
50, 100 and 200 random stops, for a 6-D tracker (5 µm, 2″) and a 3-D point tracker (10 µm);
the amplitude where it reaches 90 %; how often noise alone names anything; and full `diagnose`
runs (perturbed geometry, nonlinear model, every round and held-out check) at 3σ, 100 stops,
6-D tracker, as the check on the linearised first round `jt.detection_power` computes.

Every run: two sessions (the tracker set up anew for the second), a lab temperature that rises
5 °C over the run and cycles ±1.5 °C three times (air conditioning), and payloads of 0, 50 or
100 kg, so that every library effect and dictionary family can show. The plan (the poses) is
the same for every run of one size; noise, temperatures, payloads and, in the full checks,
the table's geometric errors are drawn afresh.

Run:  python studies/discovery_power.py [--quick] [--out DIR]
      (writes discovery_power.md and discovery_power.png into DIR, default results/)
"""

import argparse
import time
from pathlib import Path

import jax
import numpy as np

import jaxtable as jt

RESULTS = Path(__file__).resolve().parents[1] / "results"
TRACKERS = {"6-D tracker": jt.tracker6, "3-D point tracker": jt.point_tracker}
STOPS = (50, 100, 200)
AMPLITUDES = (0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0)
TARGET = 3.0  # the operating point: 3σ peak amplitude, 100 stops


def leg(i, value=1.0):
    v = np.zeros(6)
    v[i - 1] = value
    return v


CROSS_5_ON_2 = np.outer(leg(2), leg(5))
PLANTED = {
    "spiral": {"spiral": jt.Spiral(np.ones(6))},
    "lead_scale": {"lead_scale": jt.LeadScale(np.ones(6))},
    "backlash": {"backlash": jt.Backlash(np.ones(6))},
    "periodic_lead": {"periodic_lead": jt.PeriodicLead(np.ones(6), np.zeros(6))},
    "thermal": {"thermal": jt.Thermal(np.ones(6))},
    "compliance": {"compliance": jt.Compliance(np.ones(6))},
    "rehoming": {"rehoming": jt.Rehoming(np.array([[1.0, -1.0, 0.5, -0.5, 1.0, -1.0]]))},
    # one cylinder's own defect: a screw from another batch, a worn nut
    "lead_scale on leg 3 alone": {"lead_scale": jt.LeadScale(leg(3))},
    "backlash on leg 4 alone": {"backlash": jt.Backlash(leg(4))},
    "s^2 on leg 3": {"discovered": jt.Discovered(s2=leg(3))},
    "s^3 on leg 1": {"discovered": jt.Discovered(s3=leg(1))},
    "s[5] on leg 2": {"discovered": jt.Discovered(cross=CROSS_5_ON_2)},
    "d*s shared": {"discovered": jt.Discovered(ds_all=1.0)},
    "T*s shared": {"discovered": jt.Discovered(Ts_all=1.0)},
    "t on leg 1": {"discovered": jt.Discovered(t=leg(1))},
    "session*s on leg 4": {"discovered": jt.Discovered(session_s=leg(4)[None])},
}


def planted_effect(label):
    """The library effect a planted case holds; None for a dictionary term."""
    name = next(iter(PLANTED[label]))
    return None if name == "discovered" else name


LIBRARY = [k for k in PLANTED if planted_effect(k)]


def nominal_table():
    return jt.replace(jt.reference_table(), platform_mass=150.0, platform_cog=[0, 0, 60.0])


def run(nominal, true, n, tracker, effects, seed):
    """One run: the same random plan for every seed (the amplitude is a property of the plan),
    fresh noise, temperatures and payloads."""
    rng = np.random.default_rng(10_000 + seed)
    t = np.arange(n) / n
    return jt.simulate(
        nominal,
        true,
        jt.plan_random(n, 1),
        TRACKERS[tracker](),
        effects=effects,
        compensated=False,
        seed=seed,
        session=np.repeat(["1", "2"], [n // 2, n - n // 2]),
        frame=[[0, 0, 0, 0, 0, 0], [15.0, -8.0, 4.0, 0.01, -0.005, 0.02]],
        temperature=20 + 5 * t + 1.5 * np.sin(2 * np.pi * 3 * t) + rng.normal(0, 0.2, n),
        payload=rng.choice([0.0, 50.0, 100.0], n),
    )


def scaled(mods, c):
    """The planted modules with every parameter multiplied by c."""
    return {k: jax.tree.map(lambda x: c * x, m) for k, m in mods.items()}


def first_name(diag):
    """What `diagnose` named first: ('library', name), ('term', candidate) or None."""
    for step in diag.steps:
        if not step.added:
            continue
        if step.added.startswith("term "):
            return "term", diag.discovered[0].candidate
        if step.added:
            return "library", step.added_effect
    return None


def named_right(first, truth_label, truth):
    if first is None:
        return False
    kind, what = first
    if planted_effect(truth_label):
        return kind == "library" and what == planted_effect(truth_label)
    family, legs = truth
    return kind == "term" and what.family == family and set(legs) <= set(what.legs)


def truth_of(candidate_label):
    """(family, legs) of a dictionary candidate, from its label ("s^2 on leg 3",
    "d*s on legs 1-6 (shared)")."""
    term, _, where = candidate_label.partition(" on ")
    family = "s[j]" if term.startswith("s[") else term
    legs = range(1, 7) if "shared" in where else [int(where.split()[-1])]
    return family, tuple(legs)


def curves_figure(power, path):
    plt = jt.reports.pyplot()
    trackers = list(dict.fromkeys(t for t, _ in power))
    stops = list(dict.fromkeys(n for _, n in power))
    fig, axes = plt.subplots(
        len(trackers), len(stops), figsize=(5 * len(stops), 4.3 * len(trackers)), squeeze=False
    )
    colors = plt.get_cmap("tab20").colors
    for r, tracker in enumerate(trackers):
        for c, n in enumerate(stops):
            ax = axes[r, c]
            p = power[tracker, n]
            for k, label in enumerate(p.labels):
                ax.plot(
                    p.amplitudes,
                    p.correct[k],
                    "-" if label in LIBRARY else "--",
                    marker="o",
                    ms=3,
                    color=colors[k % 20],
                    label=label,
                )
            ax.axhline(0.9, color="k", lw=0.6, ls=":")
            ax.axvline(TARGET, color="k", lw=0.6, ls=":")
            ax.set_xscale("log")
            ax.set_title(
                f"{tracker}, {n} stops (noise alone names: {100 * p.false_discovery:.1f} %)",
                fontsize=9,
            )
            ax.set_xlabel("peak amplitude / σ")
            if c == 0:
                ax.set_ylabel("P(named first, correctly)")
            ax.grid(alpha=0.3)
    axes[0, -1].legend(fontsize=7, loc="lower right", ncol=2)
    fig.suptitle("diagnose's first round: library effects (solid) and dictionary terms (dashed)")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="100 stops, 6-D tracker, few trials")
    ap.add_argument("--out", type=Path, default=RESULTS, help="output folder (default results/)")
    ap.add_argument("--trials", type=int, default=2000, help="trials per amplitude")
    ap.add_argument("--checks", type=int, default=2, help="full diagnose runs per effect")
    ap.add_argument("--null-checks", type=int, default=10, help="full noise-only diagnose runs")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    trackers = ["6-D tracker"] if args.quick else list(TRACKERS)
    stops = (100,) if args.quick else STOPS
    trials = 200 if args.quick else args.trials
    nominal = nominal_table()
    power = {}
    for tracker in trackers:
        for n in stops:
            data = run(nominal, nominal, n, tracker, {}, seed=1)
            p = jt.detection_power(
                nominal, data, PLANTED, AMPLITUDES, trials=trials, draws=max(trials, 1000)
            )
            power[tracker, n] = p
            print(
                f"{tracker}, {n} stops: noise alone names {100 * p.false_discovery:.1f} % "
                f"({time.perf_counter() - t0:.0f} s)",
                flush=True,
            )

    # the check: full diagnose runs at the target amplitude
    ref = power["6-D tracker", 100]
    k_target = list(AMPLITUDES).index(TARGET)
    checks = 1 if args.quick else args.checks
    check_rows = []
    for label in ref.labels if not args.quick else ["s^2 on leg 3", "backlash"]:
        c = ref.coefficient_at(label, TARGET)
        truth = None if planted_effect(label) else truth_of(ref.truth[ref.labels.index(label)])
        hits, names = 0, []
        for s in range(checks):
            seed = 100 + s
            true = jt.perturb_table(nominal, seed, joint_sigma=0.010, zero_sigma=0.050)
            data = run(nominal, true, 100, "6-D tracker", scaled(PLANTED[label], c), seed)
            diag = jt.diagnose(nominal, data, log=lambda _: None, compensated=False)
            first = first_name(diag)
            hits += named_right(first, label, truth)
            amb = diag.as_json()["ambiguous"]
            names.append(
                ("nothing" if first is None else str(first[1]))
                + (f" [ambiguous: {'; '.join(' / '.join(g) for g in amb)}]" if amb else "")
            )
        k = ref.labels.index(label)
        check_rows.append((label, ref.correct[k, k_target], hits, checks, names))
        print(f"check {label}: {hits}/{checks} ({time.perf_counter() - t0:.0f} s)", flush=True)
    null_checks = 2 if args.quick else args.null_checks
    null_named = []
    for s in range(null_checks):
        seed = 500 + s
        true = jt.perturb_table(nominal, seed, joint_sigma=0.010, zero_sigma=0.050)
        data = run(nominal, true, 100, "6-D tracker", {}, seed)
        diag = jt.diagnose(nominal, data, log=lambda _: None, compensated=False)
        first = first_name(diag)
        null_named.append("nothing" if first is None else str(first[1]))
    n_false = sum(x != "nothing" for x in null_named)

    curves_figure(power, args.out / "discovery_power.png")
    lines = [
        "# Discovery power: the amplitude at which `diagnose` names an effect",
        "",
        "Reference table (150 kg platform), random stops in two sessions (the tracker set up "
        "anew for the second), lab temperature +5 °C over the run with a ±1.5 °C cycle, "
        "payloads 0/50/100 kg; 6-D tracker "
        "5 µm / 2″, point tracker 10 µm. Amplitude: the planted effect's largest reading "
        "change over the run, in units of that reading's σ. Probabilities: `jt.detection_power`"
        f" (diagnose's first round on its linearisation, {trials} trials per point); the "
        "check: full `diagnose` runs. Regenerate: `python studies/discovery_power.py`.",
        "",
        "## Amplitude (peak / σ) at which the effect is named first with 90 % probability",
        "",
        "| planted | " + " | ".join(f"{t}, {n}" for t in trackers for n in stops) + " |",
        "|---|" + "---|" * (len(trackers) * len(stops)),
    ]
    for label in ref.labels:
        cells = []
        for t in trackers:
            for n in stops:
                a = power[t, n].amplitude_at(label)
                cells.append("> 8" if np.isnan(a) else f"{a:.2g}")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines += [
        "",
        f"## At {TARGET:g}σ peak amplitude and 100 stops",
        "",
        "| planted | coefficient at 3σ | "
        + " | ".join(f"{t}: named right / wrong (most frequent wrong name)" for t in trackers)
        + " |",
        "|---|---|" + "---|" * len(trackers),
    ]
    meets = {t: [] for t in trackers}
    for k, label in enumerate(ref.labels):
        cells = []
        for t in trackers:
            p = power[t, 100]
            right, wrong = p.correct[k, k_target], p.wrong[k, k_target]
            meets[t].append(right >= 0.95 and wrong <= 0.01)
            w = p.wrong_names[k][k_target]
            flag = p.flagged[k, k_target]
            cells.append(
                f"{100 * right:.1f} % / {100 * wrong:.1f} %"
                + (f" ({w})" if w else "")
                + (f"; {100 * flag:.1f} % reported ambiguous with the truth" if flag else "")
            )
        lines.append(
            f"| {label} | {ref.coefficient_at(label, TARGET):.3g} | " + " | ".join(cells) + " |"
        )
    lines += [
        "",
        "Coefficients in the effect's own units (`spiral`: mm/rev of lead; `lead_scale`, "
        "`d*s`, `s[j]`, `session*s`: mm/mm; `backlash`, `t`, `periodic_lead`, `rehoming`: mm; "
        "`thermal`, `T*s`: 1/K; `compliance`: mm/N; `s^2`: 1/mm; `s^3`: 1/mm²). `spiral`, "
        "`thermal` and `compliance` compete in both forms (per leg, and one coefficient for "
        "all legs), `lead_scale`, `backlash` and `periodic_lead` also on each leg alone; any "
        'form names the effect. "Reported ambiguous with the truth": a wrong '
        "library name that the report pairs with the planted term as a finding the data "
        "cannot tell apart (with a plan to separate them).",
        "",
        "## Noise alone",
        "",
        "| run | names anything | a library effect | a dictionary term |",
        "|---|---|---|---|",
    ]
    for (t, n), p in power.items():
        lines.append(
            f"| {t}, {n} stops | {100 * p.false_discovery:.1f} % | "
            f"{100 * p.false_library:.1f} % | {100 * p.false_term:.1f} % |"
        )
    lines += [
        "",
        f"Full `diagnose` on {null_checks} noise-only runs (6-D tracker, 100 stops, perturbed "
        f"geometry): {n_false} named something first ({', '.join(sorted(set(null_named)))}).",
        "",
        f"## Check: full `diagnose` at {TARGET:g}σ, 100 stops, 6-D tracker",
        "",
        "| planted | linearised P(named right) | full diagnose: named right | first names |",
        "|---|---|---|---|",
    ]
    agree = 0
    for label, p_lin, hits, n_runs, names in check_rows:
        lines.append(f"| {label} | {100 * p_lin:.0f} % | {hits}/{n_runs} | {'; '.join(names)} |")
        expected = p_lin * n_runs
        agree += abs(hits - expected) <= max(1.0, 2 * np.sqrt(n_runs * p_lin * (1 - p_lin)))
    t6 = trackers[0]
    ok6 = [lab for lab, m in zip(ref.labels, meets[t6]) if m]
    lines += [
        "",
        "## Conclusions",
        "",
        f"- {t6}, 100 stops, {TARGET:g}σ: {len(ok6)} of {len(ref.labels)} planted effects meet "
        "the target (≥ 95 % named right, ≤ 1 % named wrong): "
        f"{', '.join(ok6) or 'none'}. The rest: "
        + "; ".join(
            f"{lab} {100 * ref.correct[k, k_target]:.0f} % right"
            + (
                f", mostly named {ref.wrong_names[k][k_target]}"
                if ref.wrong_names[k][k_target]
                else ""
            )
            + (
                f" (reported ambiguous with the truth in {100 * ref.flagged[k, k_target]:.0f} %)"
                if ref.flagged[k, k_target] >= 0.005
                else ""
            )
            for k, lab in enumerate(ref.labels)
            if lab not in ok6
        )
        + ".",
        f"- Noise alone names something in {100 * ref.false_discovery:.1f} % of linearised "
        f"runs at 100 stops (the dictionary's stated rate is 5 %); full diagnose: {n_false} of "
        f"{null_checks}.",
        f"- The full pipeline agrees with the linearised probability within binomial noise for "
        f"{agree} of {len(check_rows)} planted effects ({checks} runs each).",
    ]
    if "3-D point tracker" in trackers:
        okp = [lab for lab, m in zip(ref.labels, meets["3-D point tracker"]) if m]
        lines.append(
            f"- 3-D point tracker, 100 stops, {TARGET:g}σ: {len(okp)} of {len(ref.labels)} meet "
            "the target; without angles the frame and the geometry absorb more of each effect."
        )
    lines += ["", f"Run time {time.perf_counter() - t0:.0f} s."]
    (args.out / "discovery_power.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines[-8:]))
    print(f"wrote {args.out / 'discovery_power.md'} in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
