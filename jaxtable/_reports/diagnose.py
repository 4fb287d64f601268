"""Markdown, figures and JSON of a diagnosis (shared by `jaxtable diagnose` and studies)."""

import json
import math
from pathlib import Path

import numpy as np

from .. import _params as vocab
from .._calibration.heldout import UNDEFINED_WORDS, heldout_text
from .._calibration.measurements import Measurements, save_measurements
from .._calibration.model_file import save_fitted_model
from .._calibration.outliers import repeat_words
from .._discovery.diagnose import (
    SIGNATURE_OF,
    Diagnosis,
    group_label,
    leg_residuals,
    signatures,
)
from .._discovery.dictionary import TERMS, discrimination_plan
from .._effects import EFFECTS
from .figures import pyplot


def _binned(x, y, bins=12):
    """Mean and standard error of y in bins of x (or per distinct value when few)."""
    x, y = np.asarray(x).reshape(-1), np.asarray(y).reshape(-1)
    vals = np.unique(x)
    if len(vals) <= 6:
        groups = [x == v for v in vals]
        centres = vals
    else:
        edges = np.quantile(x, np.linspace(0, 1, bins + 1))
        idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, bins - 1)
        groups = [idx == k for k in range(bins)]
        centres = np.array([x[g].mean() if g.any() else np.nan for g in groups])
    mean = np.array([y[g].mean() if g.any() else np.nan for g in groups])
    err = np.array([y[g].std() / np.sqrt(max(g.sum(), 1)) if g.any() else np.nan for g in groups])
    return centres, mean, err


def signature_figure(diag: Diagnosis, path: Path) -> Path | None:
    """Residuals of the base fit (leg-length equivalent, mm) against every signature the
    library's effects respond to, binned means ± standard error over all legs."""
    res = leg_residuals(diag, diag.base)
    if res is None:
        return _column_figure(diag, path)
    sig = signatures(diag)
    names = [k for k in sig if k != "row"]
    plt = pyplot()
    fig, axes = plt.subplots(2, 4, figsize=(15, 6.5))
    for ax, name in zip(axes.ravel(), names + ["row"]):
        x = sig[name]
        ax.plot(x.reshape(-1), 1e3 * res.reshape(-1), ".", ms=1.5, color="0.75")
        c, m, e = _binned(x, res)
        ax.errorbar(c, 1e3 * m, 1e3 * e, fmt="o-", color="C3", ms=3)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel(name)
        ax.set_ylabel("leg residual (µm)")
    fig.suptitle(
        "Geometric model: residuals (leg-length equivalent) against the effects' signatures"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _column_figure(diag: Diagnosis, path: Path) -> Path:
    """Without all six columns: residual of each measured column against the commanded
    pose DOF with the widest range and the row."""
    cal = diag.base
    mask = diag.setup.mask
    sigma = np.where(mask, 1.0 / np.where(mask, np.asarray(diag.setup.problem.weight), 1.0), 0)
    res = -cal.residual * sigma
    cmd = diag.data.cmd_pose
    k = int(np.argmax(np.ptp(cmd, axis=0)))
    cols = np.flatnonzero(mask.any(0))
    plt = pyplot()
    fig, axes = plt.subplots(len(cols), 2, figsize=(10, 2.8 * len(cols)), squeeze=False)
    for r, c in enumerate(cols):
        unit, f = ("mm", 1.0) if c < 3 else ("arcsec", 206264.806)
        name = "x y z roll pitch yaw".split()[c]
        axes[r, 0].plot(cmd[:, k], f * res[:, c], "o", ms=3)
        axes[r, 0].set_xlabel("commanded " + "x y z roll pitch yaw".split()[k])
        axes[r, 1].plot(np.arange(len(res)), f * res[:, c], "o-", ms=3)
        axes[r, 1].set_xlabel("row")
        for a in axes[r]:
            a.set_ylabel(f"{name} residual ({unit})")
            a.axhline(0, color="k", lw=0.5)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


TERM_SIGNATURE = {
    "s^2": "extension s (mm)",
    "s^3": "extension s (mm)",
    "d*s": "extension s (mm)",
    "T*s": "temperature (°C)",
    "t": "row",
    "session*s": "session",
}


def _signature_of(added: str, sig: dict) -> tuple[str, np.ndarray]:
    """(name, (N, 6) values) of the variable a step's addition responds to: a library
    effect's signature, or a dictionary term's ("term s[5] on leg 2": leg 5's extension)."""
    if not added.startswith("term "):
        key = SIGNATURE_OF[vocab.form_effect(added)]
        return key, sig[key]
    term = added.split()[1]
    if term.startswith("s["):
        j = int(term[2:-1])
        s = sig["extension s (mm)"][:, j - 1]
        return f"extension of leg {j} (mm)", np.repeat(s[:, None], 6, axis=1)
    key = TERM_SIGNATURE[term]
    return key, sig[key]


def effect_figures(diag: Diagnosis, out: Path) -> list[Path]:
    """For each selected effect: leg residuals against its signature before it was added
    and with the final model (a one-leg form: that leg's)."""
    paths = []
    sig = signatures(diag)
    after = leg_residuals(diag, diag.final)
    if after is None:
        return paths
    plt = pyplot()
    for step in diag.steps:
        if step.added is None:
            continue
        before = leg_residuals(diag, step.fit)
        key, x = _signature_of(step.added, sig)
        leg = None if step.added.startswith("term ") else vocab.leg_of(step.added)
        legs = list(range(6)) if leg is None else [leg - 1]
        fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
        for ax, res, title in (
            (axes[0], before[:, legs], f"model {' + '.join(step.model)}"),
            (axes[1], after[:, legs], f"final model (+ {', '.join(diag.selected)})"),
        ):
            ax.plot(x[:, legs].reshape(-1), 1e3 * res.reshape(-1), ".", ms=2, color="0.7")
            c, m, e = _binned(x[:, legs], res)
            ax.errorbar(c, 1e3 * m, 1e3 * e, fmt="o-", color="C3", ms=3)
            ax.axhline(0, color="k", lw=0.5)
            ax.set_xlabel(key)
            ax.set_title(title, fontsize=9)
        axes[0].set_ylabel("leg residual (µm)" if leg is None else f"leg {leg} residual (µm)")
        fig.suptitle(
            f"{vocab.form_label(step.added)}: leg residuals against its signature, before and after"
        )
        fig.tight_layout()
        p = out / f"effect_{_slug(step.added)}.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(p)
    return paths


def _fmt_params(params: dict) -> str:
    parts = []
    for f, (v, s) in params.items():
        unit = vocab.UNITS.get(f, "")
        vals = ", ".join(
            f"{a:.3g}±{b:.2g}" if np.isfinite(b) else f"{a:.3g}±inf" for a, b in zip(v, s)
        )
        parts.append(f"{f} [{unit}] = [{vals}]")
    return "; ".join(parts)


def _dictionary_lines(diag: Diagnosis) -> list[str]:
    """The "beyond the library" section: terms found, absorbed, ambiguous."""
    if not diag.screenings:
        return []
    lines = ["## Beyond the library: the discovery dictionary", ""]
    thresholds = ", ".join(f"{s.threshold:.1f}" for s in diag.screenings)
    lines.append(
        "Each round screens every dictionary term against the current fit (score: Δχ² in "
        "units of the fit's σ minus k·ln n) and adds the best one only when it beats the "
        "dictionary-wide threshold (noise-only data give any discovery in "
        f"{100 * diag.discovery_alpha:.0f} % of data sets; thresholds this run: "
        f"{thresholds}) and pays on held-out rows."
    )
    lines.append("")
    if diag.discovered:
        lines += [
            "| term | legs | coefficient ± σ | ΔBIC | held-out gain |",
            "|---|---|---|---|---|",
        ]
        for f in diag.discovered:
            unit = TERMS[f.candidate.family].unit
            coef = ", ".join(f"{v:.3g} ± {e:.2g}" for v, e in zip(f.coefficient, f.std))
            lines.append(
                f"| `{f.candidate.term}` | {f.candidate.label} | {coef} {unit} | "
                f"{f.delta_bic:.1f} | {heldout_text(100 * f.heldout_gain, '+.1f', ' %')} |"
            )
        lines.append("")
        lines += [f"- {f.words}" for f in diag.discovered] + [""]
    else:
        lines += ["No dictionary term beats the threshold.", ""]
    if diag.absorbed:
        lines += [
            "Absorbed (within this workspace the fitted model already reproduces them; they "
            "would extrapolate wrongly outside it): " + ", ".join(f"`{t}`" for t in diag.absorbed),
            "",
        ]
    for i, group in enumerate(diag.ambiguous):
        plan = diag.plans[i] if i < len(diag.plans) else None
        library = [g for g in group if isinstance(g, str)]
        lines.append(
            "Ambiguous: "
            + " / ".join(group_label(g) for g in group)
            + " explain the data almost equally"
            + (
                f"; plan `{plan['plan']}`: {plan['plan_words']}"
                if plan and plan["plan"]
                else (f"; {plan['plan_words']}" if plan else "")
            )
            + (f"; {library[0]} is named (library effects keep priority)" if library else "")
            + "."
        )
    return lines


def markdown(diag: Diagnosis, figures: list[Path], source: str) -> str:
    lines = [
        f"# Diagnosis of {source}",
        "",
        f"{len(diag.data)} rows, measured columns: {', '.join(diag.data.measured_columns)}; "
        f"sessions: {len(diag.data.sessions)}; the drift term `t` runs over "
        f"{diag.data.clock_words()}. Start model: rigid geometry (42 parameters, "
        "joints modulo the rigid motions the instrument frame absorbs) + instrument frame per "
        "session and target offset.",
        "",
        *([repeat_words(diag.repeated) + ".", ""] if diag.repeated else []),
        *([diag.stops.words(diag.final.group_sigma()) + ".", ""] if diag.stops is not None else []),
        *(
            [
                f"**{len(diag.set_aside)} reading(s) set aside as gross errors** (measured − "
                "model fitted without them; data snooping with a robust scale, family-wise "
                "false-alarm rate 1 %; `--keep-outliers` fits them): "
                + "; ".join(g.words() for g in diag.set_aside)
                + ".",
                "",
            ]
            if diag.set_aside
            else []
        ),
        *(
            line
            for split in diag.split_sessions
            for line in (
                f"**Session split at a step in time** (`--keep-sessions` keeps the file's "
                f"sessions): {split.words()}. The fitted model holds session "
                f"'{split.label}' (its instrument frame; rehoming offsets where selected): "
                "mark those rows as a session of their own in the file.",
                "",
            )
        ),
        "**Selected effects:** "
        + (", ".join(map(vocab.form_label, diag.selected_forms)) or "none")
        + ". "
        + (
            "**Discovered terms:** " + "; ".join(f.candidate.label for f in diag.discovered) + ". "
            if diag.discovered
            else ""
        )
        + f"**Unexplained structure:** {'yes' if diag.unexplained else 'no'}: "
        + (diag.structure.words() if diag.structure is not None else "not tested")
        + f" (neighbour-agreement test, false-alarm rate {diag.alpha:g}, independent of σ's "
        "scale; σ "
        + ("as stated" if diag.noise_mode == "fixed" else "estimated for each model")
        + ")."
        + (
            f" A Gaussian-process residual model (`jt.residual_gp`"
            f"{diag.residual_model.scope()}) gains "
            f"{100 * diag.residual_model.gain:.1f} % on held-out rows; it depends most on: "
            + "; ".join(diag.residual_model.hints()[:4])
            + "."
            if diag.residual_model is not None
            else ""
        ),
        "",
        *[f"- {line}" for line in (diag.final.noise.lines() if diag.final.noise else [])],
        "",
        "| | fit RMS (units of the final model's σ) | held-out RMS (same units, k-fold) |",
        "|---|---|---|",
        f"| geometric model | {diag.rms_before:.3f} | {heldout_text(diag.heldout_rms_before)} |",
        f"| final model | {diag.rms_after:.3f} | {heldout_text(diag.heldout_rms_after)} |",
        "",
        *(
            []
            if math.isfinite(diag.heldout_rms_after)
            else [
                f"Held-out check not defined: {UNDEFINED_WORDS}; no effect is accepted without it.",
                "",
            ]
        ),
        "RMS per column (mm / rad), geometric -> final: "
        + ", ".join(
            f"{c} {diag.base.rms_after[c]:.4g} -> {diag.final.rms_after[c]:.4g}"
            for c in diag.final.rms_after
        ),
        "",
        "## Steps",
        "",
    ]
    for k, step in enumerate(diag.steps):
        lines += [
            f"### Step {k + 1}: model {' + '.join(step.model)}",
            "",
            f"χ²/dof = {step.chi2:.1f}/{step.dof}, "
            f"RMS {step.rms:.3f} σ, held-out RMS {heldout_text(step.heldout_rms, suffix=' σ')}"
            + (f" ({words})" if (words := step.noise_words()) else "")
            + "; "
            + (step.structure.words() if step.structure is not None else "")
            + f". Decision: {step.decision}.",
            "",
            "| candidate | ΔBIC | held-out gain | share of excess χ² | structure left "
            "(p) | equal legs (p) | fitted parameters |",
            "|---|---|---|---|---|---|---|",
        ]
        for c in step.candidates:
            # the structure test on the candidate's fit, where the share fell short
            left = "–" if c.structure_after is None else f"{c.structure_after:.3g}"
            # a per-leg form against its shared form: the likelihood-ratio test of equal legs
            equal = "–" if c.equal_legs_p is None else f"{c.equal_legs_p:.3g}"
            lines.append(
                f"| {vocab.form_label(c.effect)} | {c.delta_bic:.1f} | "
                f"{heldout_text(100 * c.heldout_gain, '+.1f', ' %')} | "
                f"{100 * c.share:.0f} % | {left} | {equal} | {_fmt_params(c.params)} |"
            )
        lines.append("")
    lines += _dictionary_lines(diag)
    if diag.instrument_drift is not None:
        lines += [f"**Instrument drift.** {diag.instrument_drift.words()}.", ""]
    if diag.not_applicable:
        lines += [
            "Not applicable to these data: "
            + "; ".join(f"{k} ({v})" for k, v in diag.not_applicable.items()),
            "",
        ]
    if diag.selected:
        lines += ["## Fitted effect parameters (final model, ±1σ)", ""]
        for k, form in enumerate(diag.selected_forms):
            name = vocab.form_effect(form)
            lines.append(f"- **{vocab.form_label(form)}**: {_fmt_params(diag.form_params(form))}")
            fine = diag.per_leg_candidate(name) if vocab.is_shared(form) else None
            if fine is not None:  # the ±1σ is the common value's, given equal legs
                f, (_, s) = next(iter(fine.params.items()))
                lines.append(
                    f"  (the data do not reject equal legs, p = {fine.equal_legs_p:.2g}; the "
                    f"±σ is the legs' common value's: fitted per leg, each leg's {f} has "
                    f"σ {s.min():.2g}–{s.max():.2g} {vocab.UNITS.get(f, '')}, and a leg can "
                    f"differ from the common value by a few of these σ unseen)"
                )
            if form == "lead_scale" and diag.instrument_scale is not None:
                lines.append(f"  ({diag.instrument_scale.words()})")
            if name not in map(vocab.form_effect, diag.selected_forms[k + 1 :]):
                lines.append(f"  (prior source: {EFFECTS[name].source})")
        lines.append("")
    lines += ["## Figures", ""] + [f"![{p.stem}]({p.name})" for p in figures] + [""]
    return "\n".join(lines)


def _finite(x):
    """JSON-safe copy: non-finite floats (an unidentifiable parameter's σ) become null."""
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, (np.integer, np.bool_)):
        return x.item()
    return x


def _slug(text: str) -> str:
    return "".join(ch if ch.isalnum() else "-" for ch in text).strip("-")


def step_figure(diag: Diagnosis, path: Path) -> Path | None:
    """For each session split at a step in time: the χ² a step at each row takes out of
    the residuals, per kind (the scan's profile), the row chosen, and what a linear drift
    of the same parameters takes out."""
    if not diag.split_sessions:
        return None
    plt = pyplot()
    n = len(diag.split_sessions)
    fig, axes = plt.subplots(1, n, figsize=(7 * n, 4), squeeze=False)
    for ax, split in zip(axes[0], diag.split_sessions):
        step = split.step
        for kind, (rows, chi2) in step.profile.items():
            ax.plot(rows, chi2, "-", label=f"a step of the {kind}")
        ax.axvline(step.row, color="k", lw=0.8, ls=":", label=f"row {step.row}")
        ax.axhline(step.drift_chi2, color="0.5", lw=0.8, ls="--",
                   label=f"a linear drift of the {step.kind}")  # fmt: skip
        ax.set_xlabel(f"first row after the step (session {step.session})")
        ax.set_ylabel("Δχ² taken out (whitened residuals)")
        ax.set_title(f"session '{split.label}' from row {step.row}: p = {step.p_value:.2g}")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_report(diag: Diagnosis, out: Path, source: str, json_path: Path | None = None):
    """Write report.md, figures and (optionally) the JSON into `out`; return the paths."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    figures = [signature_figure(diag, out / "residual_signatures.png")]
    figures += effect_figures(diag, out)
    figures.append(step_figure(diag, out / "session_steps.png"))
    figures = [p for p in figures if p is not None]
    plans = []
    diag.plans = []
    for group in diag.ambiguous:
        try:
            plan = discrimination_plan(diag.final, diag.setup, diag.data, group)
        except ValueError as e:  # nothing reachable to choose from
            diag.plans.append({"plan": None, "plan_words": str(e), "separates": False})
            continue
        name = "plan_" + "_vs_".join(_slug(group_label(c)) for c in group) + ".csv"
        save_measurements(Measurements(plan.poses, np.full_like(plan.poses, np.nan)), out / name)
        plans.append(name)
        diag.plans.append(
            {
                "plan": name,
                "plan_words": plan.words(),
                "separates": plan.separates,
                "correlation": [plan.correlation_before, plan.correlation_after],
                "separation_delta_chi2": [plan.separation_before, plan.separation_after],
            }
        )
        for f in diag.discovered:
            if f.candidate is group[0]:
                f.plan = name
    (out / "report.md").write_text(markdown(diag, figures, source))
    model_path = save_fitted_model(
        diag.fitted_model(),
        out / "calibrated_table.toml",
        header=f"Final model of `jaxtable diagnose` on {source}: geometry + "
        f"{', '.join(diag.model_effects) or 'no effect'}",
    )
    if json_path is not None:
        json_path = Path(json_path)
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(_finite(diag.as_json()), indent=2, allow_nan=False))
    return [out / "report.md", model_path] + figures + [out / p for p in plans]
