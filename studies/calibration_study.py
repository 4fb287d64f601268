"""Calibration study: which instrument and which poses calibrate the reference table?

Truth: the reference table with joint-centre errors (σ 10 µm per coordinate) and zero-length
errors (σ 50 µm), the passive spiral term of the hardware compensated by the controller.
Cases (all fit the paper's 42 geometric parameters, the instrument frame and target as
nuisance, joints modulo rigid motions):

- 6-D tracker (5 µm, 2 arcsec) in a shifted, tilted frame: random poses / D-optimal poses;
- 3-D point tracker (10 µm) on a target 30, −20, 80 mm off the platform origin: random /
  D-optimal poses;
- x-only laser interferometer (1 µm) on the paper's x line (−200…200 mm every 25 mm).

Reported per case: fitted and identifiable parameter counts; held-out RMS of the same
instrument on random workspace poses, before (nominal table, best instrument frame) and
after calibration (`validate` of the `fitted_model`); the TRUE pose error over random
workspace poses (exact forward kinematics of the true table vs the calibrated one for the
nominal controller's commands), absolute and as a motion error (after the best constant
frame/target transform, which no instrument in an unknown frame can see and an IMU test does
not depend on); runtime.

Pose errors are `jaxtable.pose_error` (translation difference, rotation vector).

Run:  python studies/calibration_study.py [--quick] [--out DIR]
      (writes calibration_study.md and calibration_study.png into DIR, default results/)
"""

import argparse
import time
from pathlib import Path

import numpy as np

import jaxtable as jt

RESULTS = Path(__file__).resolve().parents[1] / "results"
JOINT_SIGMA, ZERO_SIGMA = 0.010, 0.050  # the simulated truth's errors (mm)
FRAME = (50.0, -30.0, 20.0, np.deg2rad(1.2), np.deg2rad(-0.9), np.deg2rad(2.0))
FRAME_X = (50.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # an interferometer aligned with x, offset
TARGET = (30.0, -20.0, 80.0, 0.0, 0.0, 0.0)
ARCSEC = 180 * 3600 / np.pi
COLS = ("x", "y", "z", "roll", "pitch", "yaw")
FREE = jt.GEOMETRY


def fmt_cols(d: dict) -> str:
    """Per-column values (mm / rad) as µm / arcsec."""
    return ", ".join(
        f"{c} {v * (1e3 if c in COLS[:3] else ARCSEC):.2f}" for c, v in d.items() if c in COLS
    )


def rms3(e: np.ndarray) -> tuple[float, float]:
    """RMS position error (µm, over x, y, z) and rotation error (arcsec) of errors (Q, 6)."""
    return (
        float(np.sqrt(np.mean(np.sum(e[:, :3] ** 2, 1)))) * 1e3,
        float(np.sqrt(np.mean(np.sum(e[:, 3:] ** 2, 1)))) * ARCSEC,
    )


def true_errors(actual, predicted) -> np.ndarray:
    """Pose errors (Q, 6) of the `actual` poses against the `predicted` ones (both (Q, 6),
    mm / rad): `jaxtable.pose_error` (translation mm, rotation vector rad)."""
    return np.asarray(jt.pose_error(np.asarray(actual), np.asarray(predicted)))


def motion_errors(poses, errors, radius) -> np.ndarray:
    """`errors` (pose_error, rotation vector) at `poses` after removing the best constant
    base-frame and platform-target transform. `align_pose_errors` works in Euler-angle
    increments (the instruments' readings), so the rotation part goes there through the Euler
    rate matrix E (rotation vector = E @ Euler increments, to first order) and back."""
    E = np.stack([np.asarray(jt.euler_rate_matrix(q[3:])) for q in np.asarray(poses)])
    errors = np.asarray(errors, float)
    euler = np.concatenate([errors[:, :3], np.linalg.solve(E, errors[:, 3:, None])[..., 0]], 1)
    aligned = jt.align_pose_errors(poses, euler, radius)
    return np.concatenate([aligned[:, :3], (E @ aligned[:, 3:, None])[..., 0]], 1)


def noise_ratio(cal) -> str:
    """The fit's noise estimate per group as estimated σ / stated σ (`Calibration.noise`);
    χ²/dof at the stated σ where the fit did not estimate it."""
    est = getattr(cal, "noise", None)
    if est is None or not getattr(est, "estimated", False):
        return f"χ²/dof {cal.chi2 / max(cal.dof, 1):.2f}"
    return ", ".join(
        f"{n} {float(sig) / float(st):.2f}" if np.isfinite(st) else f"{n} (no stated σ)"
        for n, sig, st in zip(est.names, est.sigma, est.stated_sigma)
    )


def held_out_rms(cal, nominal, sessions, held) -> dict:
    """RMS of held-out measured − predicted per column (mm / rad) for the fitted model of
    `cal` (calibration data with session labels `sessions`): `jaxtable.validate` of
    `jaxtable.fitted_model`, the held-out rows in the calibration's instrument frame (same
    session label, so every row is a prediction)."""
    v = jt.validate(jt.fitted_model(cal, nominal, list(sessions)), held)
    return {c: (x if c in COLS[:3] else np.deg2rad(x)) for c, x in v.rms.items()}


def prepare(nominal, true, instrument, poses, frame, target, held, work, q_true, seed):
    """Simulated calibration and held-out data, the fit setup (42 parameters + nuisance) and
    the "before" state: the nominal table with the best instrument frame / target (the
    first call, which compiles the fit for this data shape)."""
    data = jt.simulate(nominal, true, poses, instrument, frame=frame, target=target, seed=seed)
    t0 = time.perf_counter()
    st = jt.setup(nominal, data, FREE)
    cal0 = jt.fit(st, free_mask=st.free_mask(()))
    t_first = time.perf_counter() - t0
    hd = jt.simulate(nominal, true, held, instrument, frame=frame, target=target, seed=seed + 1)
    e_before = true_errors(q_true, work)
    radius = float(jt.platform_radius(nominal))
    return {
        "st": st,
        "sessions": data.sessions,
        "hd": hd,
        "instrument": instrument.name,
        "poses": len(poses),
        "t_first": t_first,
        "held_before": held_out_rms(cal0, nominal, data.sessions, hd),
        "abs_before": rms3(e_before),
        "motion_before": rms3(motion_errors(work, e_before, radius)),
    }


def run_case(label, prep, nominal, work, q_true, blocks=FREE):
    """Calibrate the parameter `blocks` (a subset of FREE; the others stay nominal) on the
    prepared data and evaluate it."""
    st = prep["st"]
    mask = st.free_mask(blocks)
    before = {k: prep[k] for k in ("held_before", "abs_before", "motion_before", "t_first")}
    before["label"] = label
    t0 = time.perf_counter()
    note = ""
    try:
        cal = jt.fit(st, free_mask=mask)
    except RuntimeError as err:  # e.g. forward kinematics failing at the fitted parameters
        # the default solver failed: say so, and show what Levenberg-Marquardt gives
        note = f"default fit failed ({str(err).splitlines()[0]}); Levenberg-Marquardt shown"
        print(f"{label}: {note}", flush=True)
        try:
            cal = jt.fit(st, free_mask=mask, method="levenberg_marquardt")
        except RuntimeError as err2:
            return before | {"failed": str(err2).splitlines()[0], "fitted": int(mask.sum())}
    t_fit = time.perf_counter() - t0
    after = held_out_rms(cal, nominal, prep["sessions"], prep["hd"])
    cmd = jt.actuator_command(nominal, work)
    q_cal = np.asarray(jt.forward(cal.table, cmd, nominal=nominal, guess=work))
    e_after = true_errors(q_true, q_cal)
    radius = float(jt.platform_radius(nominal))
    row = before | {
        "instrument": prep["instrument"],
        "poses": prep["poses"],
        "fitted": len(cal.names),
        "table_params": sum(not n.startswith(("frame[", "target.")) for n in cal.names),
        "identifiable": cal.rank,
        "converged": cal.converged,
        "chi2_dof": cal.chi2 / max(cal.dof, 1),
        "noise": noise_ratio(cal),
        "held_after": after,
        "abs_after": rms3(e_after),
        "motion_after": rms3(motion_errors(work, e_after, radius)),
        "t_fit": t_fit,
        "cal": cal,
        "failed": None,
        "note": note,
    }
    print(
        f"{label}: {row['identifiable']}/{row['fitted']} identifiable, held-out "
        f"{fmt_cols(row['held_before'])} -> {fmt_cols(after)}; motion error "
        f"{row['motion_before'][0]:.1f} -> {row['motion_after'][0]:.1f} µm "
        f"(first call {row['t_first']:.1f} s, fit {t_fit:.2f} s)",
        flush=True,
    )
    return row


def figure(rows, path):
    plt = jt.reports.pyplot()
    rows = [r for r in rows if not r["failed"]]
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    x = np.arange(len(rows))
    w = 0.26
    for ax, k, unit in ((axes[0], 0, "µm"), (axes[1], 1, "arcsec")):
        for j, (key, name) in enumerate(
            (
                ("motion_before", "before (motion)"),
                ("motion_after", "after (motion)"),
                ("abs_after", "after (absolute)"),
            )
        ):
            ax.bar(x + (j - 1) * w, [r[key][k] for r in rows], w, label=name)
        ax.axhline(rows[0]["abs_before"][k], color="k", ls="--", lw=0.8, label="before (absolute)")
        ax.set_yscale("log")
        short = [
            r["label"]
            .replace("6-D tracker", "6-D")
            .replace("3-D point tracker", "3-D point")
            .replace("x interferometer", "x interf.")
            .replace("D-optimal", "D-opt")
            .replace(", ", "\n")
            for r in rows
        ]
        ax.set_xticks(x, short, fontsize=7)
        ax.set_ylabel(f"true {'position' if k == 0 else 'rotation'} error RMS ({unit})")
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle("reference table: true pose error over random workspace poses", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def better(a: float, b: float) -> str:
    """'lower' / 'higher' / 'the same' for a against b (3 significant digits)."""
    if f"{a:.3g}" == f"{b:.3g}":
        return "the same as"
    return "lower than" if a < b else "higher than"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer poses, candidates, test poses")
    ap.add_argument("--seed", type=int, default=2024, help="seed of the simulated truth")
    ap.add_argument("--out", type=Path, default=RESULTS, help="output folder (default results/)")
    args = ap.parse_args(argv)
    out = args.out
    t_start = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    nominal = jt.reference_table()
    true = jt.perturb_table(nominal, args.seed, joint_sigma=JOINT_SIGMA, zero_sigma=ZERO_SIGMA)
    if args.quick:
        n_poses, n_cand, n_work, n_held, n_random, x_step = 15, 40, 30, 30, 5, 50.0
    else:
        n_poses, n_cand, n_work, n_held, n_random, x_step = 40, 300, 300, 200, 20, 25.0
    work = jt.plan_random(n_work, args.seed + 1)
    held = jt.plan_random(n_held, args.seed + 2)
    cand = jt.plan_random(n_cand, args.seed + 3)
    rand_poses = jt.plan_random(n_poses, args.seed + 4)
    cmd = jt.actuator_command(nominal, work)
    q_true = np.asarray(jt.forward(true, cmd, nominal=nominal, guess=work))

    def data(inst, poses, frame, target=(0.0,) * 6):
        args = (nominal, true, inst, poses, frame, target, held, work, q_true)
        return prepare(*args, seed=10 * len(rows))

    def case(label, prep, blocks=FREE):
        row = run_case(label, prep, nominal, work, q_true, blocks)
        rows.append(row)
        # the first call (compilation) belongs to the first case fitted on these data
        prep["t_first"] = 0.0
        return row

    rows, designs = [], {}
    for name, inst, target in (
        ("6-D tracker", jt.tracker6(), (0.0,) * 6),
        ("3-D point tracker", jt.point_tracker(), TARGET),
    ):
        t0 = time.perf_counter()
        jac = jt.pose_jacobians(nominal, cand, inst, target=target)
        cmp = jt.compare_with_random(jac, n_poses, n_random=n_random, seed=args.seed, heldout=held)
        t_sel = time.perf_counter() - t0
        designs[name] = (cmp, t_sel)
        print(f"{name}: D-optimal {n_poses} of {n_cand} candidates in {t_sel:.1f} s", flush=True)
        prep = data(inst, rand_poses, FRAME, target)
        case(f"{name}, random {n_poses}", prep)
        if name == "3-D point tracker":
            case(f"{name}, random {n_poses}, L0 only", prep, ("zero_lengths",))
        prep = data(inst, cmp["selection"].poses, FRAME, target)
        case(f"{name}, D-optimal {n_poses}", prep)
    line = jt.plan_x_line(x_step)
    interferometer = jt.interferometer()
    prep = data(interferometer, line, FRAME_X)
    r_if = case("x interferometer, x line", prep)
    r_if0 = case("x interferometer, x line, L0 only", prep, ("zero_lengths",))
    # the interferometer held out on the x line itself (between the calibration stops)
    between = jt.plan_x_line(x_step, 200.0 - x_step / 2)
    hd = jt.simulate(nominal, true, between, interferometer, frame=FRAME_X)
    if_line = {
        r["label"]: held_out_rms(r["cal"], nominal, prep["sessions"], hd)["x"]
        for r in (r_if, r_if0)
        if not r["failed"]
    }
    total = time.perf_counter() - t_start
    # joints fitted modulo rigid motions: table parameters left per tracker
    n_table = {}
    for r in rows:
        if not r["failed"] and "L0" not in r["label"] and "tracker" in r["label"]:
            n_table.setdefault(r["table_params"], []).append(r["label"].split(",")[0])
    n_table = "; ".join(
        f"{n} with the {' and '.join(dict.fromkeys(v))}" for n, v in n_table.items()
    )

    md = [
        "# Calibration study: instruments and pose plans",
        "",
        f"`python studies/calibration_study.py{' --quick' if args.quick else ''}` "
        f"(seed {args.seed}, {total:.0f} s on this machine, CPU). Reference table; truth = "
        f"`perturb_table` (joint centres σ {JOINT_SIGMA * 1e3:g} µm per coordinate, zero "
        f"lengths σ {ZERO_SIGMA * 1e3:g} µm), the spiral term compensated by the controller. "
        "Fitted: the paper's 42 geometric parameters (joints modulo rigid motions: "
        f"{n_table or 'n/a'}), or the six zero lengths only "
        '("L0 only"), plus the instrument frame (and target) the '
        "instrument can see. Instrument frame: shifted (50, −30, 20) mm and tilted (1.2°, "
        "−0.9°, 2.0°) for the trackers; an x offset of 50 mm for the interferometer. The point "
        "tracker follows a target at (30, −20, 80) mm on the platform. Random and D-optimal "
        f"plans have the same number of poses ({n_poses}); the D-optimal ones are chosen from "
        f"{n_cand} random candidates by `jaxtable.compare_with_random` (the selection of "
        "`jaxtable.select_poses`: greedy + exchange on log det of the Fisher information of "
        "the 42-parameter fit).",
        "",
        f"## Fit and held-out residuals (same instrument, {n_held} random workspace poses; "
        "µm / arcsec)",
        "",
        "| case | fitted (table + nuisance) | identifiable | noise: σ estimated / stated "
        "| held-out RMS before | "
        "held-out RMS after | first call, incl. compile (s) | fit (s) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if r["failed"]:
            md.append(f"| {r['label']} | {r['fitted']} | fit failed: {r['failed']} ||||||")
            continue
        md.append(
            f"| {r['label']}{' (*)' if r['note'] else ''} | {r['fitted']} ({r['table_params']} + "
            f"{r['fitted'] - r['table_params']}) | {r['identifiable']} | {r['noise']} "
            f"| {fmt_cols(r['held_before'])} | {fmt_cols(r['held_after'])} | "
            f"{r['t_first']:.1f} | {r['t_fit']:.2f} |"
        )
    md += [
        "",
        '"Before": the nominal table with the instrument frame (and target) fitted to the '
        "calibration data; that first call compiles the fit (one compilation per data shape: "
        "the D-optimal and L0-only cases reuse it, the L0-only fits freeze the joints of the "
        "same setup and data). Fit: the "
        "calibration itself, compiled (Jacobian, solve, covariance, identifiability, noise "
        "estimate: `fit` rescales the stated σ of each noise group until the residuals agree "
        "with it, so χ²/dof is 1 by construction and the σ ratio is the check against the "
        "instrument's stated noise). Solver: `fit`'s default"
        + (
            '; (*) marks a case where it failed and the table shows `method="levenberg_'
            'marquardt"` instead (the failure is listed below).'
            if any(r.get("note") for r in rows)
            else " in every case."
        ),
        "",
        f"## True pose error over {n_work} random workspace poses",
        "",
        "Position: RMS of |Δt| (µm); rotation: RMS of the rotation-vector angle (arcsec) of "
        "`jaxtable.pose_error`. *Absolute*: true pose against the pose the model predicts, in "
        "the base frame. *Motion*: the same after removing the best constant base-frame and "
        "platform-target transform (`jaxtable.align_pose_errors`, applied in Euler increments "
        "through `jaxtable.euler_rate_matrix`): what an instrument in an unknown frame can "
        "check, and what an IMU test, which uses relative motions, depends on.",
        "",
        "| case | absolute before | absolute after | motion before | motion after |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        if r["failed"]:
            md.append(f"| {r['label']} | fit failed ||||")
            continue
        md.append(
            f"| {r['label']} | {r['abs_before'][0]:.1f} µm, {r['abs_before'][1]:.2f}″ | "
            f"{r['abs_after'][0]:.1f} µm, {r['abs_after'][1]:.2f}″ | "
            f"{r['motion_before'][0]:.1f} µm, {r['motion_before'][1]:.2f}″ | "
            f"{r['motion_after'][0]:.2f} µm, {r['motion_after'][1]:.2f}″ |"
        )
    notes = [f"- {r['label']}: {r['note']}" for r in rows if r.get("note")]
    if notes:
        md += ["", "Solver notes:", "", *notes]
    md += [
        "",
        "## Pose selection: D-optimal vs random (predicted from the design, 42-parameter fit)",
        "",
        "| instrument | plan | log det F | O1 | σ_min/√K | mean predicted std of the "
        "table parameters (µm) | predicted motion error x, y, z (µm) | selection time (s) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, (cmp, t_sel) in designs.items():
        for plan, r, t in (
            ("D-optimal", cmp["optimised"], f"{t_sel:.1f}"),
            (f"random (median of {n_random})", cmp["random_median"], "–"),
        ):
            md.append(
                f"| {name} | {plan} | {float(r['logdet']):.1f} | {float(r['o1']):.4f} | "
                f"{float(r['min_sv']):.2e} | {float(r['mean_std']) * 1e3:.1f} | "
                + ", ".join(f"{v * 1e3:.2f}" for v in np.asarray(r["motion_rms"])[:3])
                + f" | {t} |"
            )

    def motion(r):
        if r["failed"]:
            return "fit failed"
        return f"{r['motion_before'][0]:.1f} → {r['motion_after'][0]:.1f} µm"

    def ident(r):
        return "fit failed" if r["failed"] else f"{r['identifiable']} of {r['fitted']}"

    def held_x(r):
        return "fit failed" if r["failed"] else f"{r['held_after']['x'] * 1e3:.1f} µm"

    def gain(r):
        """'reduces' / 'increases' the true motion (position) error, or why not known."""
        if r["failed"]:
            return None
        return r["motion_after"][0] < r["motion_before"][0]

    by = {r["label"]: r for r in rows}
    t6r, t6d = by[f"6-D tracker, random {n_poses}"], by[f"6-D tracker, D-optimal {n_poses}"]
    p3r, p3d = (
        by[f"3-D point tracker, random {n_poses}"],
        by[f"3-D point tracker, D-optimal {n_poses}"],
    )
    p30 = by[f"3-D point tracker, random {n_poses}, L0 only"]
    noise_if = interferometer.noise[0] * 1e3

    # x interferometer: what the line determines and what fitting it does to the workspace
    if r_if["failed"]:
        if_verdict = f" The 42-parameter fit failed ({r_if['failed']})."
    else:
        full_rank = r_if["identifiable"] == r_if["fitted"]
        worse = not gain(r_if)
        if_verdict = (
            " The paper's experiment checks the table along x; "
            + (
                "its data determine every fitted combination"
                if full_rank
                else f"it determines only {r_if['identifiable']} of the {r_if['fitted']} "
                "fitted combinations, so it cannot calibrate the workspace"
            )
            + (
                ", and fitting it makes the workspace worse (true motion error up): the solver "
                "moves directions the line cannot determine"
                + (" (see the solver notes)" if r_if["note"] else "")
                + "."
                if worse
                else ", and here fitting it does not make the workspace worse (true motion "
                "error down)."
            )
        )
    line_rms = ", ".join(
        f"{v * 1e3:.2f} µm ({'L0 only' if 'L0' in k else '42 parameters'})"
        for k, v in if_line.items()
    )
    line_vs_noise = (
        f" ({'at' if max(if_line.values()) * 1e3 < 1.5 * noise_if else 'above'} the "
        f"{noise_if:g} µm noise)"
        if if_line
        else ""
    )

    # 6-D tracker: D-optimal vs random, measured (one realisation) and predicted
    d6 = designs["6-D tracker"][0]
    pred_opt = float(np.sqrt(np.mean(np.asarray(d6["optimised"]["motion_rms"])[:3] ** 2)))
    pred_rand = float(np.sqrt(np.mean(np.asarray(d6["random_median"]["motion_rms"])[:3] ** 2)))
    if t6r["failed"] or t6d["failed"]:
        six_cmp = "one of the fits failed."
    else:
        six_cmp = (
            f"in this realisation the D-optimal plan's motion error is "
            f"{better(t6d['motion_after'][0], t6r['motion_after'][0])} the random plan's; the "
            f"design predicts it {better(pred_opt, pred_rand)} the median random plan's."
        )

    # 3-D point tracker: predicted parameter std against the true errors
    std3 = float(designs["3-D point tracker"][0]["random_median"]["mean_std"]) * 1e3
    lo_err, hi_err = JOINT_SIGMA * 1e3, ZERO_SIGMA * 1e3
    std_vs = "above" if std3 > hi_err else ("below" if std3 < lo_err else "within the range of")
    g3 = gain(p3r)
    rule_holds = g3 is not None and (std3 > hi_err) == (not g3)
    three = (
        f"- 3-D point tracker, {n_poses} poses: {ident(p3r)} identifiable; the fitted "
        f"table parameters have a mean predicted std of {std3:.0f} µm (random plans), "
        f"{std_vs} the true errors of {lo_err:g}–{hi_err:g} µm; true motion error "
        f"{motion(p3r)} (random), {motion(p3d)} (D-optimal), {motion(p30)} (L0 only). "
    )
    if g3 is not None:
        three += (
            f"The 42-parameter fit {'reduces' if g3 else 'increases'} the motion error"
            + (
                f"; the L0-only fit {'also ' if gain(p30) == g3 else ''}"
                f"{'reduces' if gain(p30) else 'increases'} it"
                if gain(p30) is not None
                else ""
            )
            + ". A calibration is only worth its parameters when their predicted std is below "
            "the errors it should remove"
            + (
                "; this case agrees with that rule"
                if rule_holds
                else "; here that rule alone does not predict the outcome"
            )
            + ": check `Calibration.std` (or the design's prediction) before trusting a fit."
        )

    # absolute vs motion error after calibration, trackers
    trackers = [r for r in (t6r, t6d, p3r, p3d) if not r["failed"]]
    abs_up = [r for r in trackers if r["abs_after"][0] > r["abs_before"][0]]
    motion_down = [r for r in abs_up if gain(r)]
    if motion_down:
        abs_note = (
            " For "
            + ", ".join(r["label"] for r in motion_down)
            + " the absolute error grows while the motion error falls: with the instrument "
            "frame estimated, near-rigid combinations of zero lengths and joints (moving the "
            "platform almost uniformly) are weakly determined; they hardly change the motion "
            "error but need a frame registered to the base to be fixed."
        )
    elif not abs_up:
        abs_note = " Calibration does not increase the absolute error for any tracker case."
    else:
        abs_note = (
            " The absolute error grows for "
            + ", ".join(r["label"] for r in abs_up)
            + ", and so does the motion error."
        )

    md += [
        "",
        "## Findings (numbers from the tables above)",
        "",
        f"- x interferometer on the x line ({len(line)} readings): {ident(r_if)} fitted "
        f"parameter combinations identifiable with the 42-parameter model, {ident(r_if0)} with "
        f"L0 only. Held out on the line between the stops, x RMS {line_rms or 'n/a'}"
        f"{line_vs_noise}; on random workspace poses {held_x(r_if)} (L0 only {held_x(r_if0)}) "
        f"against {r_if0['held_before']['x'] * 1e3:.1f} µm before; true motion error "
        f"{motion(r_if)} (L0 only: {motion(r_if0)})." + if_verdict,
        f"- 6-D tracker, {n_poses} poses: {ident(t6r)} identifiable; true motion error "
        f"{motion(t6r)} (random), {motion(t6d)} (D-optimal); one realisation each, against "
        "the predicted motion error per column (x, y, z) of "
        + ", ".join(f"{v * 1e3:.2f}" for v in np.asarray(d6["optimised"]["motion_rms"])[:3])
        + " µm (D-optimal) and "
        + ", ".join(f"{v * 1e3:.2f}" for v in np.asarray(d6["random_median"]["motion_rms"])[:3])
        + " µm (median random plan): "
        + six_cmp,
        three,
        "- Absolute (base-frame) error after calibration: "
        + ", ".join(f"{r['label']} {r['abs_after'][0]:.0f} µm" for r in trackers)
        + f" against {t6r['abs_before'][0]:.0f} µm before."
        + abs_note,
        "",
        "Figure: calibration_study.png (true position / rotation error per case, log scale).",
        "",
    ]
    text = "\n".join(md)
    (out / "calibration_study.md").write_text(text)
    figure(rows, out / "calibration_study.png")
    print(text)
    print(f"total {time.perf_counter() - t_start:.0f} s")


if __name__ == "__main__":
    main()
