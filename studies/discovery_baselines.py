"""Discovery against two baselines: LASSO with cross-validation over the same dictionary, and a
Gaussian-process residual model as the ceiling of held-out gain.

The runs of `discovery_power.py`'s check (reference table, 100 random stops, 6-D tracker, two
sessions with the tracker set up anew, temperature ramp with an air-conditioning cycle,
payloads, perturbed geometry), each effect planted alone at 3σ peak amplitude, and
noise-only runs. On every run:

- `diagnose` (the full pipeline): is the first name the planted effect; its held-out gain
  (grouped folds: five contiguous stretches of the run) of the final model over the base fit
  (geometry and frames), and the parameters it adds per finding;
- LASSO-CV: the base fit's linearisation, every library-effect parameter and every
  dictionary coefficient as penalised columns (unit norm), geometry and frames unpenalised
  (profiled out on each training set), λ chosen by the same grouped folds (the λ of least
  held-out error, as LassoCV does); what it names is every column left non-zero;
- the GP residual model (`jt.residual_gp`: an additive GP over the legs' extensions,
  direction, temperature, time, session and payload, fitted with the geometry by REML): its
  held-out gain on the same folds.

Target (issue 13): ≥ 90 % of the GP's held-out gain with ≤ 2 parameters per finding.

Run:  python studies/discovery_baselines.py [--quick] [--seeds N] [--out DIR]
      (writes discovery_baselines.md, .png and .json (every run's figures) into DIR, default
      results/; 20 min on 2 cores; `--from-json results/discovery_baselines.json` rewrites
      the report from the saved runs)
"""

import argparse
import json
import re
import time
from pathlib import Path

import numpy as np
from discovery_power import (
    PLANTED,
    TARGET,
    first_name,
    named_right,
    nominal_table,
    planted_effect,
    run,
    scaled,
    truth_of,
)

import jaxtable as jt

RESULTS = Path(__file__).resolve().parents[1] / "results"
FOLDS = 5
FAMILY = {"s2": "s^2", "s3": "s^3", "cross": "s[j]", "ds": "d*s", "Ts": "T*s", "t": "t"}
FAMILY["session_s"] = "session*s"


def column_owner(key: str):
    """(kind, name, legs) of a parameter key: ('library', effect, legs) or ('term', family,
    legs) — `discovered.cross[2].5` -> ('term', 's[j]', (2,)), `discovered.ds_all` -> ('term',
    'd*s', (1..6))."""
    effect, _, rest = key.partition(".")
    if effect != "discovered":
        return "library", effect, ()
    m = re.match(r"(\w+?)(_all)?(?:\[(\d+)\])?(?:\.(\d+))?$", rest)
    field, shared, first, second = m.groups()
    fam = FAMILY[field]
    if fam == "s[j]":
        j = int(first)
        legs = tuple(i for i in range(1, 7) if i != j) if shared else (int(first),)
        return "term", f"s[{second or first}]" if not shared else f"s[{j}]", legs
    if fam == "session*s":
        return "term", fam, tuple(range(1, 7)) if shared else (int(second),)
    return "term", fam, tuple(range(1, 7)) if shared else (int(first),)


def lasso_path(X, y, lams, iters=400):
    """FISTA solutions (len(lams), p) of min ½‖y − Xβ‖² + λ‖β‖₁ along a decreasing path."""
    G, c = X.T @ X, X.T @ y
    L = max(np.linalg.eigvalsh(G)[-1], 1e-12)
    beta = np.zeros(X.shape[1])
    out = []
    for lam in lams:
        z, t = beta.copy(), 1.0
        for _ in range(iters):
            g = z - (G @ z - c) / L
            new = np.sign(g) * np.maximum(np.abs(g) - lam / L, 0.0)
            t_new = 0.5 * (1 + np.sqrt(1 + 4 * t * t))
            z = new + (t - 1) / t_new * (new - beta)
            beta, t = new, t_new
        out.append(beta.copy())
    return np.array(out)


def lasso_cv(diag):
    """LASSO-CV on the base fit's linearisation: (selected keys, held-out gain at the chosen
    λ over the base model on the grouped folds)."""
    base, st = diag.base, diag.setup
    mask = np.asarray(st.mask, bool)
    n = mask.shape[0]
    obs = np.flatnonzero(mask.reshape(-1))
    y = np.asarray(base.residual).reshape(-1)[obs]
    J = np.asarray(base.jacobian)[obs]
    keys = [k for k in st.names if "." in k and k.split(".")[0] in set(jt.EFFECTS) | {"discovered"}]
    idx = [st.names.index(k) for k in keys]
    X = np.asarray(base.jacobian_full)[obs][:, idx]
    norm = np.linalg.norm(X, axis=0)
    live = norm > 1e-12 * norm.max()
    X, keys = X[:, live] / norm[live], [k for k, ok in zip(keys, live) if ok]

    def profiled(rows):
        U = np.linalg.svd(J[rows], full_matrices=False)[0]
        return lambda A: A - U @ (U.T @ A)

    P = profiled(np.arange(len(obs)))
    Xp, yp = P(X), P(y)
    lam_max = float(np.max(np.abs(Xp.T @ yp)))
    lams = lam_max * np.logspace(0, -3, 30)
    pos = np.full(n * 6, -1)
    pos[obs] = np.arange(len(obs))
    err = np.zeros(len(lams))
    for block in np.array_split(np.arange(n), FOLDS):
        f = pos[(block[:, None] * 6 + np.arange(6)).reshape(-1)]
        f = f[f >= 0]
        t = np.setdiff1d(np.arange(len(obs)), f)
        Pt = profiled(t)
        B = lasso_path(Pt(X[t]), Pt(y[t]), lams)  # (L, p)
        gam = np.linalg.lstsq(J[t], y[t][:, None] - X[t] @ B.T, rcond=1e-10)[0]
        pred = J[f] @ gam + X[f] @ B.T
        err += np.sum((y[f][:, None] - pred) ** 2, axis=0)
    k = int(np.argmin(err))
    beta = lasso_path(Xp, yp, lams[: k + 1])[-1]
    gain = 1.0 - np.sqrt(err[k] / err[0])  # err[0]: λ_max, nothing selected
    return [key for key, b in zip(keys, beta) if b != 0.0], float(gain)


def lasso_verdict(selected, label, truth):
    """(named right, wrong names) of LASSO's selection for the planted `label`."""
    owners = [column_owner(k) for k in selected]
    if label is None:
        return False, len({(o[0], o[1]) for o in owners})
    effect = planted_effect(label)
    if effect:
        right = any(o[0] == "library" and o[1] == effect for o in owners)
        wrong = {(o[0], o[1]) for o in owners if not (o[0] == "library" and o[1] == effect)}
        return right, len(wrong)
    family, legs = truth
    ours = [o for o in owners if o[0] == "term" and truth_of_owner(o) == family]
    covered = set().union(*[set(o[2]) for o in ours]) if ours else set()
    right = set(legs) <= covered
    wrong = {(o[0], o[1]) for o in owners if o not in ours or not set(o[2]) <= set(legs)}
    return right, len(wrong)


def truth_of_owner(o):
    return "s[j]" if o[1].startswith("s[") else o[1]


def model_gain(diag):
    """Held-out gain of the final model over the base fit on the grouped folds (the base
    fit's σ units), and the free parameters it added."""
    base, final, mask = diag.base, diag.final, diag.setup.mask
    blocks = np.array_split(np.arange(len(diag.data)), FOLDS)
    to_base = np.where(mask, base.weight / np.where(mask, final.weight, 1.0), 0.0)
    h0 = jt.heldout_rms(base, blocks, mask)
    h1 = jt.heldout_rms(final, blocks, mask, rescale=to_base)
    return 1.0 - h1 / h0, final.rank - base.rank


def one(nominal, label, coef, seed):
    true = jt.perturb_table(nominal, seed, joint_sigma=0.010, zero_sigma=0.050)
    planted = {} if label is None else scaled(PLANTED[label], coef)
    data = run(nominal, true, 100, "6-D tracker", planted, seed)
    diag = jt.diagnose(nominal, data, log=lambda _: None, compensated=False)
    first = first_name(diag)
    truth = None if label is None or planted_effect(label) else truth_of(TRUTH[label])
    right = False if label is None else named_right(first, label, truth)
    gain, added = model_gain(diag)
    findings = len(diag.selected) + len(diag.discovered)
    selected, l_gain = lasso_cv(diag)
    l_right, l_wrong = lasso_verdict(selected, label, truth)
    gp = jt.residual_gp(diag.base, diag.setup, folds=FOLDS)
    return {
        "right": right,
        "named": first is not None,
        "gain": gain,
        "params": added / findings if findings else 0.0,
        "lasso_right": l_right,
        "lasso_wrong": l_wrong,
        "lasso_size": len(selected),
        "lasso_gain": l_gain,
        "gp_gain": gp.gain,
        "gp_hint": next(iter(gp.components), ""),
    }


TRUTH = {}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="two planted effects, one seed each")
    ap.add_argument("--seeds", type=int, default=6, help="runs per planted effect")
    ap.add_argument("--null", type=int, default=12, help="noise-only runs")
    ap.add_argument("--out", type=Path, default=RESULTS, help="output folder (default results/)")
    ap.add_argument(
        "--from-json",
        type=Path,
        help="write the report from a saved discovery_baselines.json (no runs)",
    )
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if args.from_json:
        saved = json.loads(args.from_json.read_text())
        rows, null, run_time = saved["planted"], saved["noise_only"], saved["run_time_s"]
    else:
        rows, null = compute(args, t0)
        run_time = time.perf_counter() - t0
        (args.out / "discovery_baselines.json").write_text(
            json.dumps(
                {"planted": rows, "noise_only": null, "run_time_s": run_time},
                indent=1,
                default=float,
            )
        )
    report(rows, null, run_time, args.out)


def compute(args, t0):
    """Every run: {label: [run figures]} for the planted effects, [run figures] on noise."""
    nominal = nominal_table()
    labels = ["s^2 on leg 3", "backlash"] if args.quick else list(PLANTED)
    seeds = 1 if args.quick else args.seeds
    n_null = 1 if args.quick else args.null
    plan = run(nominal, nominal, 100, "6-D tracker", {}, seed=1)
    power = jt.detection_power(
        nominal, plan, {k: PLANTED[k] for k in labels}, [TARGET], trials=1, draws=100
    )
    TRUTH.update(dict(zip(power.labels, power.truth)))
    rows = {}
    for label in labels:
        c = power.coefficient_at(label, TARGET)
        rows[label] = [one(nominal, label, c, 100 + s) for s in range(seeds)]
        print(f"{label}: {time.perf_counter() - t0:.0f} s", flush=True)
    null = [one(nominal, None, 0.0, 500 + s) for s in range(n_null)]
    print(f"noise only: {time.perf_counter() - t0:.0f} s", flush=True)
    return rows, null


def report(rows, null, run_time, out):
    seeds = len(next(iter(rows.values())))
    n_null = len(null)

    def mean(rs, k):
        return float(np.mean([r[k] for r in rs]))

    lines = [
        "# Discovery against LASSO-CV and a Gaussian-process ceiling",
        "",
        f"Each effect planted alone at {TARGET:g}σ peak amplitude in {seeds} runs of 100 random "
        "stops (6-D tracker 5 µm / 2″, two sessions with the tracker set up anew, temperature "
        "ramp and cycle, payloads, perturbed geometry), and "
        f"{n_null} noise-only runs. Held-out gains: 1 − RMS(model) / RMS(base fit) of the "
        f"σ-normalised residuals on {FOLDS} grouped folds (contiguous stretches of the run). "
        "Regenerate: `python studies/discovery_baselines.py`.",
        "",
        "| planted | diagnose: named right | LASSO-CV: planted among its names | LASSO-CV: "
        "wrong names per run (columns kept) | held-out gain: diagnose | LASSO-CV | GP ceiling "
        "| diagnose / GP | parameters per finding | GP's strongest component |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    ratios, params_ok = {}, {}
    gp_noise = max(mean(null, "gp_gain"), 0.0)  # what the GP gains on noise alone
    for label, rs in rows.items():
        g, gp = mean(rs, "gain"), mean(rs, "gp_gain")
        ratios[label] = g / gp if gp > max(2 * gp_noise, 0.005) else float("nan")
        params_ok[label] = mean(rs, "params")
        hints = sorted({r["gp_hint"] for r in rs})
        lines.append(
            f"| {label} | {sum(r['right'] for r in rs)}/{len(rs)} | "
            f"{sum(r['lasso_right'] for r in rs)}/{len(rs)} | {mean(rs, 'lasso_wrong'):.1f} "
            f"({mean(rs, 'lasso_size'):.0f}) | {100 * g:.1f} % | "
            f"{100 * mean(rs, 'lasso_gain'):.1f} % | {100 * gp:.1f} % | "
            + ("–" if np.isnan(ratios[label]) else f"{100 * ratios[label]:.0f} %")
            + f" | {params_ok[label]:.1f} | {'; '.join(hints[:2])} |"
        )
    lines.append(
        f"| noise only | {sum(r['named'] for r in null)}/{len(null)} named something | "
        f"{sum(r['lasso_wrong'] > 0 for r in null)}/{len(null)} kept a column | "
        f"{mean(null, 'lasso_wrong'):.1f} ({mean(null, 'lasso_size'):.0f}) | "
        f"{100 * mean(null, 'gain'):.1f} % | {100 * mean(null, 'lasso_gain'):.1f} % | "
        f"{100 * mean(null, 'gp_gain'):.1f} % | – | – | – |"
    )
    ok = [k for k, r in ratios.items() if r >= 0.9 and params_ok[k] <= 2.0]
    measured = [k for k, r in ratios.items() if not np.isnan(r)]
    terms = [k for k in measured if not planted_effect(k)]
    ok_terms = [k for k in ok if k in terms]
    weak = [
        f"{k} (diagnose {100 * mean(rows[k], 'gain'):.1f} %, GP "
        f"{100 * mean(rows[k], 'gp_gain'):.1f} %)"
        for k in rows
        if k not in measured
    ]
    low = [f"{k} ({100 * ratios[k]:.0f} %)" for k in measured if ratios[k] < 0.9]
    lines += [
        "",
        "Gains are means over the runs; diagnose / GP is the ratio of the means (– where the GP "
        f"gains less than twice what it gains on noise alone, {100 * gp_noise:.1f} %: nothing "
        "to compare). Parameters per finding: free parameters the final model adds over the "
        "base fit, per effect or term it names.",
        "",
        "## Conclusions",
        "",
        f"- Target (≥ 90 % of the GP's held-out gain with ≤ 2 parameters per finding): met by "
        f"{len(ok_terms)} of the {len(terms)} dictionary terms the GP gains on "
        f"({', '.join(ok_terms) or 'none'}) and {len(ok) - len(ok_terms)} of the "
        f"{len(measured) - len(terms)} library effects "
        f"({', '.join(k for k in ok if k not in ok_terms) or 'none'}; the others gain less "
        "or are named in a per-leg form: one parameter per leg or more, as each nut and "
        "screw has its own)."
        + (
            f" Too weak to compare (the GP gains under twice its noise): {'; '.join(weak)}."
            if weak
            else ""
        ),
        f"- diagnose over the GP, median over the {len(measured)} planted effects the GP "
        f"gains on: {100 * np.nanmedian([ratios[k] for k in measured]):.0f} %"
        + (f"; below 90 %: {', '.join(low)}." if low else "."),
        f"- LASSO-CV names the planted effect among its columns in "
        f"{sum(r['lasso_right'] for rs in rows.values() for r in rs)} of "
        f"{sum(len(rs) for rs in rows.values())} runs, but keeps "
        f"{np.mean([r['lasso_size'] for rs in rows.values() for r in rs]):.0f} columns on "
        f"average and names something on noise alone in "
        f"{sum(r['lasso_wrong'] > 0 for r in null)} of {len(null)} runs "
        f"(diagnose: {sum(r['named'] for r in null)}): cross-validation chooses λ for "
        "prediction, not for a false-discovery rate.",
        f"- On noise alone the GP gains {100 * mean(null, 'gp_gain'):.1f} % on average "
        f"(diagnose {100 * mean(null, 'gain'):.1f} %, LASSO-CV "
        f"{100 * mean(null, 'lasso_gain'):.1f} %): its hyper-parameters are fitted on every "
        "row, so its ceiling sits about that much high, which makes the ratios above "
        "conservative for diagnose.",
        "- The GP is no ceiling where the effect is not smooth on the scale ~100 stops "
        "resolve: "
        + (", ".join(f"{k} ({100 * r:.0f} %)" for k, r in ratios.items() if r > 2) or "none")
        + " — a named form extrapolates where a flexible model cannot.",
        "",
        f"Run time {run_time:.0f} s.",
    ]
    figure(rows, null, out / "discovery_baselines.png")
    (out / "discovery_baselines.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines[-10:]))
    print(f"wrote {out / 'discovery_baselines.md'}")


def figure(rows, null, path):
    plt = jt.reports.pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 5.5))
    top = 0.0
    for label, rs in rows.items():
        x = [100 * r["gp_gain"] for r in rs]
        y = [100 * r["gain"] for r in rs]
        top = max(top, *x, *y)
        ax.plot(x, y, "o" if planted_effect(label) else "^", ms=5, label=label, alpha=0.8)
    ax.plot(
        [100 * r["gp_gain"] for r in null],
        [100 * r["gain"] for r in null],
        "kx",
        label="noise only",
    )
    ax.plot([0, top], [0, top], "k-", lw=0.6)
    ax.plot([0, top], [0, 0.9 * top], "k:", lw=0.6, label="90 % of the GP")
    ax.set_xlabel("GP residual model: held-out gain (%)")
    ax.set_ylabel("diagnose's final model: held-out gain (%)")
    ax.set_title("held-out gain on grouped folds, 3σ effects, 100 stops", fontsize=9)
    ax.legend(fontsize=6, ncol=2)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    main()
