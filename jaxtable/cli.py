"""Command line: `jaxtable <verb>`. Every verb takes --table FILE (default: the embedded
reference table) and writes its figures and a Markdown report into --out DIR."""

import argparse
import sys
from pathlib import Path

from ._data import DataFileError
from ._errors import KinematicsError, TableFileError
from ._tolerance import ToleranceFileError


def _table(path):
    from ._io import load_table, reference_table

    return reference_table() if path is None else load_table(path)


def _spiral(args) -> int:
    from ._spiral_report import spiral_report

    table = _table(args.table)
    print(
        f"computing the passive spiral term of '{table.name}' "
        f"({args.samples} random workspace poses) ...",
        file=sys.stderr,
    )
    text = spiral_report(table, args.out, n_random=args.samples)
    print(text)
    print(f"wrote {Path(args.out) / 'spiral.md'} and 3 figures", file=sys.stderr)
    return 0


class UsageError(ValueError):
    """A malformed command-line value."""


def _parse_fixed(text: str, flag: str = "--fixed") -> list[float]:
    """'z=-50,yaw=5' -> 6 values in file units (mm / deg), others 0."""
    from ._errors import POSE_COLUMNS

    fixed = [0.0] * 6
    for item in filter(None, (t.strip() for t in text.split(","))):
        name, _, value = item.partition("=")
        if name not in POSE_COLUMNS:
            raise UsageError(f"{flag}: unknown DOF '{name}' in '{item}'")
        try:
            fixed[POSE_COLUMNS.index(name)] = float(value)
        except ValueError:
            raise UsageError(f"{flag}: '{item}' is not DOF=number") from None
    return fixed


def _map(args) -> int:
    from ._errormap import error_map, workspace_slice
    from ._map_report import budget_chart, slice_figures, summary_markdown, x_stroke_figure
    from ._tolerance import Tolerances, load_tolerances

    table = _table(args.table)
    tol = Tolerances() if args.tolerances is None else load_tolerances(args.tolerances)
    dofs = tuple(d.strip() for d in args.slice.split(","))
    if len(dofs) != 2:
        raise UsageError(f"--slice takes two DOF, e.g. x,y; got '{args.slice}'")
    try:
        grid = workspace_slice(dofs, args.n, fixed=_parse_fixed(args.fixed))
    except ValueError as e:
        raise UsageError(str(e)) from None
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    emap, summary = error_map(table, tol, grid, progress=True)
    stem = f"map_{dofs[0]}_{dofs[1]}"
    slice_figures(table, emap, out, stem)
    x_stroke_figure(table, tol, out)
    budget_chart(summary, out)
    text = "\n".join(
        [
            f"# Error map: {table.name}",
            "",
            "Tolerances (file units): "
            + ", ".join(f"{k} = {v:g}" for k, v in tol.as_dict().items()),
            "",
            summary_markdown(summary, f"{dofs[0]}-{dofs[1]} slice, {args.n} x {args.n} poses"),
            f"Figures: {stem}.png, error_x_stroke.png, error_budget.png",
            "",
        ]
    )
    (out / "map.md").write_text(text)
    print(text)
    return 0


def _pose_arg(text: str, flag: str) -> list[float]:
    """'x=50,yaw=2' (mm / deg) -> 6 values in mm / rad."""
    import numpy as np

    vals = np.asarray(_parse_fixed(text, flag), dtype=float)
    vals[3:] = np.deg2rad(vals[3:])
    return vals.tolist()


def _simulate(args) -> int:

    from ._data import save_measurements
    from ._instrument import INSTRUMENTS
    from ._io import save_table
    from ._simulate import perturb_table, plan_grid, plan_random, plan_swing, plan_x_line
    from ._simulate import simulate as run

    table = _table(args.table)
    true = perturb_table(table, args.seed, args.joint_sigma, args.zero_sigma)
    plans = {
        "random": lambda: plan_random(args.n, args.seed),
        "x_line": plan_x_line,
        "grid": lambda: plan_grid(3),
        "swing": lambda: plan_swing("roll", 5.0, 2.0, args.n),
    }
    poses = plans[args.plan]()
    print(
        f"simulating {len(poses)} stops of '{table.name}' with a {args.instrument} ...",
        file=sys.stderr,
    )
    data = run(
        table,
        true,
        poses,
        INSTRUMENTS[args.instrument](),
        compensate=not args.uncompensated,
        frame=_pose_arg(args.frame, "--frame"),
        target=_pose_arg(args.target, "--target"),
        seed=args.seed,
    )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    save_measurements(data, out / "data.csv")
    save_table(
        true,
        out / "true_table.toml",
        header="The simulated hardware (nominal table + sampled errors); keep it away "
        "from the calibration.",
    )
    print(
        f"wrote {out / 'data.csv'} ({len(data)} rows, columns "
        f"{', '.join(data.measured_columns)}) and {out / 'true_table.toml'}"
    )
    return 0


def _calibrate(args) -> int:
    import numpy as np

    from ._calibrate import fit, setup
    from ._data import load_measurements
    from ._io import save_table
    from ._table import replace

    table = _table(args.table)
    data = load_measurements(args.data)
    free = tuple(f.strip() for f in args.free.split(",") if f.strip())
    print(f"calibrating {', '.join(free)} on {len(data)} rows ...", file=sys.stderr)
    try:
        st = setup(
            table,
            data,
            free,
            compensated=not args.uncompensated,
            estimate_frame=not args.no_frame,
        )
        cal = fit(st)
    except ValueError as e:
        print(f"jaxtable calibrate: error: {args.data}: {e}", file=sys.stderr)
        return 2
    fitted = cal.table
    if "spiral" in cal.effects:
        lead = np.asarray(cal.effects["spiral"].lead)
        fitted = replace(fitted, lead=np.abs(lead), hand=np.where(lead < 0, -1.0, 1.0))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    save_table(
        fitted,
        out / "calibrated_table.toml",
        header=f"Calibrated from {args.data} (free: {', '.join(free)}); joint centres "
        "are fitted modulo rigid motions where the instrument frame was "
        "estimated (see report.md).",
        effects=cal.effects,
    )
    rows = [f"| {n} | {v:+.5g} | {s:.3g} |" for n, v, s in zip(cal.names, cal.value, cal.std)]
    frames = "\n".join(
        f"- session {lab}: "
        + ", ".join(f"{c} {v:+.4f}" for c, v in zip("x y z".split(), cal.frame[k, :3]))
        + " mm, "
        + ", ".join(
            f"{c} {np.rad2deg(v):+.5f}°" for c, v in zip("roll pitch yaw".split(), cal.frame[k, 3:])
        )
        for k, lab in enumerate(data.sessions)
    )
    text = "\n".join(
        [
            f"# Calibration of {table.name} from {args.data}",
            "",
            "```",
            cal.report(),
            "```",
            "",
            "Instrument frame (pose of the base frame in the instrument frame) per session:",
            "",
            frames,
            "",
            "| parameter (change from nominal) | value | σ |",
            "|---|---|---|",
            *rows,
            "",
        ]
    )
    from ._diagnose import _folds, heldout_rms

    folds = _folds(len(data), 5, 0)
    text += (
        f"\nHeld-out check (5-fold: each fifth of the rows predicted by the fit to the rest): "
        f"RMS {heldout_rms(cal, folds, st.mask):.3f} σ, against "
        f"{float(np.sqrt(np.mean(cal.residual[st.mask] ** 2))):.3f} σ on the fitted rows "
        "(1.0 = the instrument noise).\n"
    )
    if args.mcmc:
        from ._posterior import corner_plot, plot_bands, posterior, predictive_bands
        from ._simulate import plan_x_line

        post = posterior(st, cal, n_steps=args.steps, seed=0, progress=True)
        corner_plot(post, out / "corner.png")
        bands = predictive_bands(st, post, plan_x_line(), n_samples=100)
        plot_bands(bands, out / "bands.png")
        text += "\n".join(
            [
                "",
                "## Posterior (emcee)",
                "",
                "```",
                post.summary(),
                "```",
                "",
                "![corner](corner.png)",
                "",
                "Posterior-predictive pose error along the x stroke (nominal controller, "
                "sampled tables):",
                "",
                "![bands](bands.png)",
                "",
            ]
        )
    (out / "report.md").write_text(text)
    print(cal.report())
    print(f"wrote {out / 'calibrated_table.toml'} and {out / 'report.md'}", file=sys.stderr)
    return 0


def _diagnose(args) -> int:
    from ._data import load_measurements
    from ._diagnose import diagnose
    from ._diagnose_report import write_report
    from ._effects import EFFECTS

    table = _table(args.table)
    if args.data is None:
        from importlib import resources

        ref = resources.files("jaxtable") / "data" / "example_measurements.csv"
        with resources.as_file(ref) as path:
            data = load_measurements(path)
        source = "the bundled example data (simulated)"
    else:
        data = load_measurements(args.data)
        source = str(args.data)
    base = tuple(b.strip() for b in args.base.split(",") if b.strip())
    library = tuple(b.strip() for b in args.effects.split(",") if b.strip()) or tuple(EFFECTS)
    for name in base + library:
        if name not in EFFECTS:
            raise UsageError(f"unknown effect '{name}'; known: {', '.join(EFFECTS)}")
    out = Path(args.out)
    json_path = Path(args.json) if args.json else out / "diagnosis.json"
    try:
        diag = diagnose(
            data,
            table,
            base=base,
            library=library,
            compensated=args.compensated,
            alpha=args.alpha,
            folds=args.folds,
        )
    except ValueError as e:
        raise UsageError(f"{source}: {e}") from None
    paths = write_report(diag, out, source, json_path)
    print(
        f"selected: {', '.join(diag.selected) or 'none'}; unexplained: "
        f"{str(diag.unexplained).lower()}; RMS {diag.rms_before:.3f} -> {diag.rms_after:.3f} "
        f"sigma, held-out {diag.heldout_rms_before:.3f} -> {diag.heldout_rms_after:.3f} sigma"
    )
    print(f"wrote {json_path} and {', '.join(str(p) for p in paths)}", file=sys.stderr)
    return 0


def _bench(args) -> int:
    from ._bench import markdown, run_benchmark, write

    r = run_benchmark(_table(args.table), quick=args.quick, log=lambda m: print(m, file=sys.stderr))
    print(markdown(r))
    paths = write(r, args.out)
    print(f"wrote {', '.join(str(p) for p in paths)}", file=sys.stderr)
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="jaxtable", description=__doc__)
    sub = p.add_subparsers(dest="verb", required=True)

    def common(sp, out_default):
        sp.add_argument(
            "--table",
            type=Path,
            default=None,
            help="table file (TOML); default: the embedded reference table",
        )
        sp.add_argument(
            "--out",
            type=Path,
            default=Path(out_default),
            help=f"output directory (default: {out_default})",
        )

    sp = sub.add_parser(
        "spiral",
        help="passive spiral term: Fig. 5/6 re-drawn, pose error "
        "with and without compensation along x and over the workspace",
    )
    common(sp, "out/spiral")
    sp.add_argument(
        "--samples",
        type=int,
        default=20000,
        help="random poses in the combined-motion box (default 20000)",
    )
    sp.set_defaults(func=_spiral)

    sp = sub.add_parser(
        "map",
        help="workspace error map: linear propagation of a tolerance "
        "budget over a 2-D slice, with figures",
    )
    common(sp, "out/map")
    sp.add_argument(
        "--tolerances",
        type=Path,
        default=None,
        help="tolerance file (TOML); default: the paper's budget",
    )
    sp.add_argument("--slice", default="x,y", help="two DOF to grid (default x,y)")
    sp.add_argument("--n", type=int, default=101, help="points per slice axis (default 101)")
    sp.add_argument("--fixed", default="", help="the other DOF, e.g. 'z=-50,yaw=5' (mm, deg)")
    sp.set_defaults(func=_map)

    sp = sub.add_parser(
        "simulate",
        help="simulate a real table (nominal + sampled errors) "
        "measured by an instrument; writes data.csv and true_table.toml",
    )
    common(sp, "out/simulate")
    sp.add_argument(
        "--instrument", choices=["tracker6", "point3", "interferometer"], default="tracker6"
    )
    sp.add_argument("--plan", choices=["random", "x_line", "grid", "swing"], default="random")
    sp.add_argument("--n", type=int, default=100, help="poses (random, swing)")
    sp.add_argument("--seed", type=int, default=0)
    sp.add_argument("--joint-sigma", type=float, default=0.010, help="mm (default 0.010)")
    sp.add_argument("--zero-sigma", type=float, default=0.050, help="mm (default 0.050)")
    sp.add_argument("--frame", default="", help="instrument frame, e.g. 'x=50,yaw=2' (mm, deg)")
    sp.add_argument("--target", default="", help="target on the platform, e.g. 'z=80'")
    sp.add_argument(
        "--uncompensated",
        action="store_true",
        help="the controller does not compensate the spiral term",
    )
    sp.set_defaults(func=_simulate)

    sp = sub.add_parser(
        "calibrate",
        help="fit parameters to a measurement CSV (LM), with "
        "covariance and an identifiability report",
    )
    sp.add_argument("data", type=Path, help="measurement CSV")
    common(sp, "out/calibrate")
    sp.add_argument(
        "--free",
        default="base_joints,platform_joints,zero_lengths",
        help="comma-separated free parameters (table leaves or effect.field, e.g. spiral.lead)",
    )
    sp.add_argument(
        "--no-frame",
        action="store_true",
        help="data are in the base frame: do not estimate the instrument frame",
    )
    sp.add_argument(
        "--uncompensated",
        action="store_true",
        help="without cmd_l columns: the controller did not compensate the spiral",
    )
    sp.add_argument(
        "--mcmc",
        action="store_true",
        help="also sample the posterior with emcee (corner plot, predictive bands)",
    )
    sp.add_argument("--steps", type=int, default=2000, help="emcee steps per walker (2000)")
    sp.set_defaults(func=_calibrate)

    sp = sub.add_parser(
        "diagnose",
        help="model discovery: fit the geometric model, test its residuals, name the "
        "effect(s) responsible from the library, and measure the gain on held-out data",
    )
    sp.add_argument(
        "data",
        type=Path,
        nargs="?",
        default=None,
        help="measurement CSV (default: the bundled example data set, simulated)",
    )
    common(sp, "out/diagnose")
    sp.add_argument("--json", default=None, help="JSON result (default: OUT/diagnosis.json)")
    sp.add_argument(
        "--base", default="", help="effects already in the starting model, e.g. 'spiral'"
    )
    sp.add_argument("--effects", default="", help="candidate effects (default: the whole library)")
    sp.add_argument(
        "--compensated",
        action="store_true",
        help="without cmd_l columns: the controller compensated the spiral term",
    )
    sp.add_argument(
        "--alpha", type=float, default=0.01, help="false-alarm rate of the χ² test (0.01)"
    )
    sp.add_argument("--folds", type=int, default=5, help="k of the k-fold held-out score (5)")
    sp.set_defaults(func=_diagnose)

    sp = sub.add_parser(
        "bench",
        help="benchmarks with numpy/scipy baselines in the same run: inverse and forward "
        "kinematics, sensitivities, calibration, emcee, single-pose latency, a 1e8-pose map",
    )
    common(sp, "out/bench")
    sp.add_argument("--quick", action="store_true", help="tiny sizes: a smoke run (~1 min)")
    sp.set_defaults(func=_bench)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (TableFileError, KinematicsError, ToleranceFileError, DataFileError, UsageError) as e:
        print(f"jaxtable {args.verb}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
