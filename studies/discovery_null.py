"""False discoveries of the whole `jaxtable diagnose` pipeline on noise-only data.

Each data set is a 150-stop run of the reference table (150 kg platform) read by a 6-D
tracker (5 µm, 2″): fresh geometric errors (joints σ 10 µm, L0 σ 50 µm), a fresh random
plan, two sessions (the tracker set up anew, at a fresh offset, for the second half), a lab
temperature rising 5 °C over the run with a ±1.5 °C air-conditioning cycle, payloads of 0, 50
or 100 kg, and the tracker's noise: the geometric model is all there is. The controller
commands the rigid inverse kinematics, and the true table has no spiral term
(`effects={}`), so that every library effect is absent too. The full diagnosis runs on
each: geometry refit, library candidates with held-out checks, structure test, dictionary
rounds.

A claim is anything diagnose reports beyond the geometry: a library effect selected, a
dictionary term discovered, or `unexplained`. Its stated rate is the dictionary's 5 %
(`discovery_alpha`) plus the structure test's 1 % (`alpha`). Two conditions, the data sets
drawn alike: the file's σ columns (the true σ) stated, and no σ columns at all (σ
estimated from the fit, as a lab file usually is), half of the data sets each.

Run:  python studies/discovery_null.py [--quick] [--seeds N] [--out DIR]
      (writes discovery_null.md into DIR, default results/)
"""

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np
from scipy.stats import beta

import jaxtable as jt

RESULTS = Path(__file__).resolve().parents[1] / "results"
STOPS = 150
STATED_RATE = 0.05 + 0.01  # dictionary threshold + structure test


def noise_only(seed: int) -> tuple[jt.Table, jt.Measurements]:
    rng = np.random.default_rng(seed)
    nominal = jt.replace(jt.reference_table(), platform_mass=150.0, platform_cog=[0.0, 0.0, 60.0])
    true = jt.perturb_table(nominal, seed, joint_sigma=0.010, zero_sigma=0.050)
    k = np.arange(STOPS) / STOPS
    temperature = 20 + 5 * k + 1.5 * np.sin(2 * np.pi * 3 * k) + rng.normal(0, 0.1, STOPS)
    frames = [np.zeros(6), np.r_[rng.normal(0, 20, 3), rng.normal(0, 0.01, 3)]]
    data = jt.simulate(
        nominal,
        true,
        jt.plan_random(STOPS, seed),
        jt.tracker6(),
        effects={},
        compensated=False,
        session=np.where(k < 0.5, "a", "b"),
        frame=frames,
        temperature=temperature,
        payload=rng.choice([0.0, 50.0, 100.0], STOPS),
        seed=seed,
    )
    return nominal, data


def claims(diag) -> list[str]:
    return (
        list(diag.selected)
        + [f"term {f.candidate.label}" for f in diag.discovered]
        + (["unexplained"] if diag.unexplained else [])
    )


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    a = (1 - level) / 2
    lo = 0.0 if k == 0 else float(beta.ppf(a, k, n - k + 1))
    hi = 1.0 if k == n else float(beta.ppf(1 - a, k + 1, n - k))
    return lo, hi


def run(seeds: range) -> dict:
    """Data sets of even seeds keep their σ columns, odd ones lose them: each data set is
    diagnosed once, so the two conditions are independent samples."""
    out = {"stated σ (file)": [], "no σ columns": []}
    aside = {c: [] for c in out}  # readings set aside as gross errors, per data set
    t0 = time.perf_counter()
    for i, seed in enumerate(seeds):
        nominal, data = noise_only(seed)
        if seed % 2:
            cond, data = "no σ columns", dataclasses.replace(data, sigma=None)
        else:
            cond = "stated σ (file)"
        diag = jt.diagnose(nominal, data, log=lambda _: None)
        out[cond].append(claims(diag))
        aside[cond].append(len(diag.set_aside or []))
        if (i + 1) % 20 == 0 or i + 1 == len(seeds):
            done = {c: sum(bool(x) for x in v) for c, v in out.items()}
            print(
                f"  {i + 1}/{len(seeds)} data sets, {time.perf_counter() - t0:.0f} s; "
                f"with a claim: {done}",
                flush=True,
            )
    return out, aside


def report(out: dict, aside: dict, seconds: float) -> tuple[str, list[str]]:
    lines = [
        "# False discoveries of `jaxtable diagnose` on noise-only data",
        "",
        f"`python studies/discovery_null.py` ({seconds / 60:.0f} min on 2 cores). "
        + __doc__.split("\n\n")[1].replace("\n", " "),
        "",
        "| condition | data sets | with any claim | rate | 95 % interval | library effect | "
        "dictionary term | unexplained | lost a reading |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    conclusions = []
    for cond, sets in out.items():
        n = len(sets)
        k = sum(bool(s) for s in sets)
        lo, hi = clopper_pearson(k, n)
        lib = sum(any(c in jt.EFFECTS for c in s) for s in sets)
        term = sum(any(c.startswith("term ") for c in s) for s in sets)
        unex = sum("unexplained" in s for s in sets)
        lines.append(
            f"| {cond} | {n} | {k} | {k / n:.1%} | {lo:.1%}–{hi:.1%} | {lib} | {term} | {unex} "
            f"| {sum(a > 0 for a in aside[cond])} |"
        )
        verdict = (
            "consistent with"
            if lo <= STATED_RATE <= hi
            else ("below" if hi < STATED_RATE else "above")
        )
        conclusions.append(
            f"{cond}: {k} of {n} noise-only data sets drew a claim ({k / n:.1%}, 95 % interval "
            f"{lo:.1%}–{hi:.1%}), {verdict} the stated {STATED_RATE:.0%}."
        )
    lines += ["", "What was claimed, per data set with a claim:", ""]
    for cond, sets in out.items():
        named = [", ".join(s) for s in sets if s]
        counts = {x: named.count(x) for x in sorted(set(named))}
        lines.append(
            f"- {cond}: "
            + ("; ".join(f"{x} ({c}×)" for x, c in counts.items()) if counts else "nothing")
        )
    n_all = sum(len(v) for v in out.values())
    k_all = sum(bool(x) for v in out.values() for x in v)
    lo, hi = clopper_pearson(k_all, n_all)
    conclusions.append(
        f"all {n_all} data sets: {k_all} drew a claim ({k_all / n_all:.1%}, 95 % interval "
        f"{lo:.1%}–{hi:.1%}) against the stated {STATED_RATE:.0%}."
    )
    lost = sum(a > 0 for v in aside.values() for a in v)
    lo, hi = clopper_pearson(lost, n_all)
    conclusions.append(
        f"gross-error screen: {lost} of {n_all} clean data sets lost a reading "
        f"({lost / n_all:.1%}, 95 % interval {lo:.1%}–{hi:.1%}) against its stated 1 % "
        "(the last column)."
    )
    lines += ["", "Conclusions:", ""] + [f"- {c}" for c in conclusions] + [""]
    return "\n".join(lines), conclusions


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="4 data sets (a smoke run)")
    p.add_argument("--seeds", type=int, default=200, help="data sets (half per condition)")
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args()
    jt.enable_compilation_cache()
    n = 4 if args.quick else args.seeds
    t0 = time.perf_counter()
    out, aside = run(range(5000, 5000 + n))
    text, conclusions = report(out, aside, time.perf_counter() - t0)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "discovery_null.md").write_text(text)
    for c in conclusions:
        print(c)
    print(f"wrote {args.out / 'discovery_null.md'}")


if __name__ == "__main__":
    main()
