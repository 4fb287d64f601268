"""What a log with several readings a stop says: the tracker's noise, the table's
repeatability, and no false structure.

Each table (the reference table with random geometric errors) stops at 50 random poses and
a 6-D tracker (5 µm, 2″ a reading) reads each stop k times in a row. The table's own error
at a stop (its repeatability: where the legs settled this time) is shared by the stop's
readings: σ_r in positions, σ_r / 5 µm × 1″ in angles. The study fits each data set
twice, with the geometric model that is right: row by row (`jt.setup` and `jt.fit` on the
file as it is) and as `jaxtable calibrate` does, each stop once at the mean of its readings
(`Calibration.data`). It counts the structure test's claims (p < 0.05) both ways, and
compares the noise within a stop and the repeatability `calibrate` reports with the truth.

Run:  python studies/repeatability.py [--quick] [--tables N] [--out DIR]
      (writes repeatability.md and repeatability.png into DIR, default results/)
"""

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np
from discovery_null import clopper_pearson as interval

import jaxtable as jt

RESULTS = Path(__file__).resolve().parents[1] / "results"
STOPS = 50
READINGS = (1, 3, 5)  # readings a stop
REPEAT_UM = (0.0, 3.0)  # the table's repeatability at a stop, positions
POS_UM, ANG_ARCSEC = 5.0, 2.0  # the tracker's σ a reading


def one(k: int, rep_um: float, seed: int) -> dict:
    """Structure claimed row by row and merged; within-stop σ and repeatability (µm)."""
    nominal = jt.reference_table()
    true = jt.perturb_table(nominal, 100 + seed)
    plan = np.repeat(jt.plan_random(STOPS, 200 + seed), k, axis=0)
    d = jt.simulate(nominal, true, plan, jt.tracker6(), seed=300 + seed)
    rng = np.random.default_rng(400 + seed)
    scale = np.r_[[rep_um * 1e-3] * 3, [np.deg2rad(rep_um / POS_UM * 1.0 / 3600)] * 3]
    shared = np.repeat(rng.standard_normal((STOPS, 6)) * scale, k, axis=0)
    d = dataclasses.replace(d, measured=d.measured + shared, sigma=None)
    st = jt.setup(nominal, d, jt.GEOMETRY)
    row_by_row = jt.structure_test(jt.fit(st), st).p_value
    cal = jt.calibrate(nominal, d)
    st = jt.setup(nominal, cal.data, jt.GEOMETRY)
    merged = jt.structure_test(jt.fit(st), st).p_value
    out = {"row_by_row": row_by_row < 0.05, "merged": merged < 0.05}
    if cal.stops is not None:
        info = cal.stops.as_json(cal.group_sigma())
        out["within_um"] = info["within_sigma"]["positions"] * 1e3
        out["repeat_um"] = info["repeatability"]["positions"] * 1e3
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="2 tables (a smoke run)")
    ap.add_argument("--tables", type=int, default=None, help="tables (default 40)")
    ap.add_argument("--out", default=str(RESULTS))
    args = ap.parse_args()
    n = args.tables or (2 if args.quick else 40)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    results = {}
    for k in READINGS:
        for rep in REPEAT_UM:
            runs = [one(k, rep, seed) for seed in range(n)]
            results[k, rep] = runs
            print(f"k = {k}, σ_r = {rep:g} µm: {n} tables", flush=True)
    seconds = time.perf_counter() - t0

    def count(k, rep, key):
        return int(sum(r[key] for r in results[k, rep]))

    def spread(k, rep, key):
        v = np.array([r[key] for r in results[k, rep] if key in r])
        return f"{v.mean():.2f} ± {v.std(ddof=1):.2f}" if len(v) > 1 else "–"

    rows = []
    for (k, rep), runs in results.items():
        a, b = count(k, rep, "row_by_row"), count(k, rep, "merged")
        lo, hi = interval(a, n)
        rows.append(
            f"| {k} | {rep:g} | {a}/{n} ({lo:.2f}-{hi:.2f}) | {b}/{n} | "
            f"{spread(k, rep, 'within_um')} | {spread(k, rep, 'repeat_um')} |"
        )
    worst = max((count(k, r, "merged") for k, r in results), default=0)
    several = [(k, r) for k, r in results if k > 1 and r > 0]
    conclusions = [
        "- Row by row, readings of a stop that share the table's error at it are taken for "
        "structure: "
        + ", ".join(f"k = {k}, σ_r = {r:g} µm: {count(k, r, 'row_by_row')}/{n}" for k, r in several)
        + " data sets claimed (the model is right).",
        f"- Each stop fitted once at its mean, at most {worst}/{n} data sets in any row "
        "claimed structure (the test's α is 5 %).",
        "- The noise within a stop estimates the tracker's "
        f"{POS_UM:g} µm with no model: "
        + ", ".join(f"k = {k}: {spread(k, r, 'within_um')} µm" for k, r in several)
        + "; the repeatability at a stop, 3 µm true: "
        + ", ".join(f"k = {k}: {spread(k, r, 'repeat_um')} µm" for k, r in several)
        + ".",
    ]
    text = "\n".join(
        [
            "# Several readings a stop: the tracker's noise, the table's repeatability",
            "",
            f"{n} tables per row (reference table, perturbed), {STOPS} random stops each "
            f"read k times by a 6-D tracker ({POS_UM:g} µm, {ANG_ARCSEC:g}″ a reading), the "
            "table's error at a stop σ_r shared by its readings. Structure claimed at "
            "p < 0.05 with the right geometric model, fitted row by row and each stop once "
            "at its mean (`jaxtable calibrate`); the within-stop σ and the repeatability "
            "`calibrate` reports (mean ± sd over the tables, positions, µm). "
            f"`python studies/repeatability.py --tables {n}`, {seconds:.0f} s.",
            "",
            "| k | σ_r (µm) | structure, row by row (95 % interval) | structure, merged | "
            "within-stop σ (µm) | repeatability (µm) |",
            "|---|---|---|---|---|---|",
            *rows,
            "",
            *conclusions,
            "",
            "![structure claims](repeatability.png)",
            "",
        ]
    )
    (out / "repeatability.md").write_text(text)
    plt = jt.reports.pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.8))
    for key, style in (("row_by_row", "o-"), ("merged", "s--")):
        for rep in REPEAT_UM:
            rate = [count(k, rep, key) / n for k in READINGS]
            ax.plot(READINGS, rate, style, label=f"{key.replace('_', ' ')}, σ_r = {rep:g} µm")
    ax.axhline(0.05, color="grey", lw=0.8, ls=":")
    ax.set_xlabel("readings a stop, k")
    ax.set_ylabel("share of data sets: structure claimed")
    ax.set_ylim(-0.05, 1.05)
    ax.set_xticks(READINGS)
    ax.legend(fontsize=8)
    ax.set_title("the right model, several readings a stop", fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "repeatability.png", dpi=100)
    plt.close(fig)
    print("\n".join(conclusions))
    print(f"wrote {out / 'repeatability.md'}, {out / 'repeatability.png'}")


if __name__ == "__main__":
    main()
