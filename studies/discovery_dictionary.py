"""Discovery beyond the library: errors nobody listed, planted in simulated 6-D tracker runs of
the reference table, and what `jaxtable diagnose` says about each.

Every case: the reference table with random geometric errors (joints σ 10 µm, L0 σ 50 µm),
150 random stops, a 6-D tracker (10 µm, 2 arcsec), temperature and payload columns, the
controller uncompensated for the passive term the hardware does not have here. Planted:
one dictionary term per family at a realistic magnitude (per leg or shared), a library
effect for contrast, and noise-only runs that must yield nothing. For each: what is named
(library or term, legs, coefficient against the truth), its held-out gain and what
compensating with it buys the commanded pose, what is absorbed or ambiguous, and whether
structure remains.

Run:  python studies/discovery_dictionary.py [--quick] [--out DIR]
      (writes discovery_dictionary.md into DIR, default results/)
"""

import argparse
import time
from pathlib import Path

import numpy as np

import jaxtable as jt

RESULTS = Path(__file__).resolve().parents[1] / "results"
N = 150


def cross(i, j, c):
    m = np.zeros((6, 6))
    m[i - 1, j - 1] = c
    return m


# name: (effects, expected name, true coefficient(s) or None, extra simulate kwargs)
CASES = {
    "s^2 on leg 3 (screw sag)": (
        {"discovered": jt.Discovered(s2=[0, 0, 3e-6, 0, 0, 0])},
        "s^2",
        [3e-6],
        {},
    ),
    "s[5] on leg 2 (crosstalk)": (
        {"discovered": jt.Discovered(cross=cross(2, 5, 2e-3))},
        "s[5]",
        [2e-3],
        {},
    ),
    "T*s shared (thermal scale)": (
        {"discovered": jt.Discovered(Ts_all=1.5e-5)},
        "T*s",
        [1.5e-5],
        {},
    ),
    "d*s shared (direction scale)": (
        {"discovered": jt.Discovered(ds_all=1e-4)},
        "d*s",
        [1e-4],
        {},
    ),
    "t on leg 1, cycling lab temperature (drift)": (
        {"discovered": jt.Discovered(t=[0.02, 0, 0, 0, 0, 0])},
        "t",
        [0.02],
        {"temperature": 21 + 2 * np.sin(2 * np.pi * 3 * np.arange(N) / N)},
    ),
    "t on leg 1, temperature rising with the run": (
        {"discovered": jt.Discovered(t=[0.02, 0, 0, 0, 0, 0])},
        "t",
        [0.02],
        {},
    ),
    "backlash (library effect)": (
        {"backlash": jt.Backlash(np.full(6, 0.025))},
        "backlash",
        None,
        {},
    ),
}
QUICK = ("s^2 on leg 3 (screw sag)", "backlash (library effect)")


def simulate(effects, seed, **kw):
    nominal = jt.replace(jt.reference_table(), platform_mass=150.0, platform_cog=[0, 0, 60.0])
    true = jt.perturb_table(nominal, seed, joint_sigma=0.010, zero_sigma=0.050)
    rng = np.random.default_rng(1000 + seed)
    kw.setdefault("temperature", 20 + 10 * np.arange(N) / N + rng.normal(0, 0.2, N))
    kw.setdefault("payload", rng.choice([0.0, 50.0, 100.0], N))
    data = jt.simulate(
        nominal,
        true,
        jt.plan_random(N, seed),
        jt.tracker6(),
        effects=effects,
        compensated=False,
        seed=seed,
        **kw,
    )
    return nominal, data


def describe(diag) -> str:
    parts = [f"library: {', '.join(diag.selected) or 'none'}"]
    for f in diag.discovered:
        coef = ", ".join(f"{v:.3g} ± {e:.1g}" for v, e in zip(f.coefficient, f.std))
        parts.append(f"term `{f.candidate.term}` on {f.candidate.label.split(' on ')[1]}: {coef}")
    return "; ".join(parts)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="two cases, 3 null runs")
    ap.add_argument("--out", type=Path, default=RESULTS, help="output folder (default results/)")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    cases = {k: v for k, v in CASES.items() if not args.quick or k in QUICK}
    n_null = 3 if args.quick else 20
    rows, named_right, lines_words = [], 0, []
    for k, (name, (effects, expected, truth, kw)) in enumerate(cases.items()):
        nominal, data = simulate(effects, 5 + k, **kw)
        diag = jt.diagnose(nominal, data, log=lambda _: None, compensated=False)
        names = list(diag.selected) + [f.candidate.term for f in diag.discovered]
        hit = bool(names) and names[0] == expected
        z = ""
        if hit and truth is not None:
            f = diag.discovered[0]
            z = ", ".join(f"{v:+.1f}" for v in (f.coefficient - np.asarray(truth)) / f.std)
        named_right += hit
        gain = diag.discovered[0].heldout_gain if diag.discovered else None
        doc = diag.as_json()
        ambiguous = "; ".join(" / ".join(g["candidates"]) for g in doc["ambiguous_detail"])
        rows.append(
            f"| {name} | {describe(diag)} | {z or '–'} | "
            f"{'–' if gain is None else f'{-100 * gain:+.1f} %'} | "
            f"{', '.join(diag.absorbed) or '–'} | {ambiguous or '–'} | {diag.unexplained} |"
        )
        lines_words += [f"- {name}: {f.words}" for f in diag.discovered]
    false = 0
    for seed in range(n_null):
        nominal, data = simulate({}, 300 + seed)
        diag = jt.diagnose(nominal, data, log=lambda _: None, compensated=False)
        false += bool(diag.selected or diag.discovered or diag.unexplained)
    lines = [
        "# Discovery beyond the library (simulated 6-D tracker runs, reference table)",
        "",
        f"{N} random stops per run; joints σ 10 µm, L0 σ 50 µm; tracker 10 µm / 2 arcsec. "
        "Regenerate: "
        f"`python studies/discovery_dictionary.py{' --quick' if args.quick else ''}`.",
        "",
        "| planted | named by `diagnose` | (fit − truth)/σ | held-out RMS | absorbed | "
        "ambiguous | unexplained |",
        "|---|---|---|---|---|---|---|",
        *rows,
        "",
        "What the findings say:",
        "",
        *lines_words,
        "",
        f"- {named_right} of {len(cases)} planted errors are named first as what was planted "
        "(a drift planted while the temperature rises with the run counts as missed when "
        "`thermal` is named instead: the data cannot tell them apart, and the report says so).",
        f"- Noise-only runs: {false} of {n_null} yield any library effect, term or "
        "unexplained structure (the dictionary's threshold keeps its own rate at 5 %, the "
        "structure test at 1 %).",
        "",
    ]
    text = "\n".join(lines)
    (args.out / "discovery_dictionary.md").write_text(text)
    print(text)
    print(f"total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
