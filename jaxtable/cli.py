"""Command line: `jaxtable <verb>`. Every verb takes --table FILE (default: the embedded
reference table) and writes its figures and a Markdown report into --out DIR."""

import argparse
import math
import sys
import warnings
from pathlib import Path

from ._analysis.tolerances import ToleranceFileError
from ._analysis.workspaces import WorkspaceFileError
from ._cache import enable_compilation_cache
from ._calibration.heldout import UNDEFINED_WORDS, heldout_text
from ._calibration.measurements import DataFileError
from ._errors import KinematicsError, TableFileError
from ._params import GEOMETRY, form_label


def _table(path):
    from ._io import load_table, reference_table

    return reference_table() if path is None else load_table(path)


def _spiral(args) -> int:
    from ._reports.spiral import spiral_report

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


def _whole(least: int):
    """argparse type: a whole number of at least `least` (argparse names the option)."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not a whole number") from None
        if v < least:
            raise argparse.ArgumentTypeError(f"{v} is below the least value, {least}")
        return v

    return parse


def _number(low: float, *, above: bool = False, below: float | None = None):
    """argparse type: a finite number ≥ `low` (> `low` with `above`; < `below` if given)."""

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not a number") from None
        ok = math.isfinite(v) and (v > low if above else v >= low)
        if not ok or (below is not None and not v < below):
            rule = f"{'above' if above else 'at least'} {low:g}" + (
                f" and below {below:g}" if below is not None else ""
            )
            raise argparse.ArgumentTypeError(f"{text} is not {rule}")
        return v

    return parse


def _names(text: str, flag: str) -> tuple[str, ...]:
    """'a, b,c' -> ('a', 'b', 'c'); refuses a name given twice, or a field in both its forms
    (`params.check_distinct`), naming the option."""
    from . import _params as params

    names = tuple(t.strip() for t in text.split(",") if t.strip())
    try:
        params.check_distinct(names, "name")
    except ValueError as e:
        raise UsageError(f"{flag}: {e}") from None
    return names


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
    from ._analysis.errormap import error_map
    from ._analysis.tolerances import Tolerances, load_tolerances
    from ._analysis.workspaces import workspace_slice
    from ._reports.errormap import write_map_report

    table = _table(args.table)
    tol = Tolerances() if args.tolerances is None else load_tolerances(args.tolerances)
    dofs = tuple(d.strip() for d in args.slice.split(","))
    if len(dofs) != 2:
        raise UsageError(f"--slice takes two DOF, e.g. x,y; got '{args.slice}'")
    try:
        grid = workspace_slice(dofs, args.n, fixed=_parse_fixed(args.fixed))
    except ValueError as e:
        raise UsageError(str(e)) from None
    emap, summary = error_map(table, tol, grid, progress=True)
    if summary["reachable"] == 0:
        raise UsageError(
            f"none of the {summary['poses']} poses of the {dofs[0]}-{dofs[1]} slice"
            + (f" ({args.fixed})" if args.fixed else "")
            + " is reachable (a leg outside its stroke or a joint past its bend limit "
            "everywhere): nothing to map; choose --fixed inside the workspace"
        )
    text = write_map_report(table, tol, emap, summary, args.out, dofs, args.n)
    print(text)
    return 0


def _sigma_arg(text: str | None) -> dict | None:
    """--sigma 'x=0.01,roll=2arcsec' or an instrument preset (tracker6, point3,
    interferometer) -> {column: σ (mm / rad)}."""
    from ._calibration.instruments import INSTRUMENTS
    from ._calibration.noise import parse_sigma
    from ._params import POSE

    if not text:
        return None
    if text in INSTRUMENTS:
        inst = INSTRUMENTS[text]()
        return {POSE[k]: float(inst.noise[k]) for k in inst.columns}
    try:
        return parse_sigma(text)
    except ValueError as e:
        raise UsageError(str(e)) from None


def _pose_arg(text: str, flag: str) -> list[float]:
    """'x=50,yaw=2' (mm / deg) -> 6 values in mm / rad."""
    from ._params import pose_from_file

    return pose_from_file(_parse_fixed(text, flag)).tolist()


def _simulate(args) -> int:

    from ._calibration.instruments import INSTRUMENTS
    from ._calibration.measurements import save_measurements
    from ._calibration.simulate import (
        perturb_table,
        plan_grid,
        plan_random,
        plan_swing,
        plan_x_line,
    )
    from ._calibration.simulate import simulate as run
    from ._io import save_table

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
        compensated=args.compensated,
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


def _prior(value):
    """`--prior`: None (no prior), "paper" (the paper's tolerances) or a tolerance file."""
    from ._analysis.tolerances import Tolerances, load_tolerances

    if value is None:
        return None
    if value == "paper":
        return Tolerances()
    path = Path(value)
    if not path.is_file():
        raise UsageError(f"--prior: '{value}' is neither 'paper' nor a tolerance file")
    return load_tolerances(path)


def _calibrate(args) -> int:
    from ._calibration.fit import check_physical, fit_screened
    from ._calibration.measurements import load_measurements
    from ._calibration.posterior import posterior, predictive_bands
    from ._calibration.simulate import plan_x_line
    from ._discovery.structure import TooFewRowsError, structure_test
    from ._reports.calibrate import write_calibration_report

    free = _names(args.free, "--free")
    if args.frame_drift and args.no_frame:
        raise UsageError("--frame-drift: the instrument frame is not estimated (--no-frame)")
    table = _table(args.table)
    prior = _prior(args.prior)
    data = load_measurements(args.data)
    print(f"calibrating {', '.join(free)} on {len(data)} rows ...", file=sys.stderr)
    if args.table is not None:
        note = _fitted_model_note(args.table, table)
        if note:
            print(note, file=sys.stderr)
    try:
        st, cal = fit_screened(
            table,
            data,
            free,
            compensated=args.compensated,
            estimate_frame=not args.no_frame,
            sigma=_sigma_arg(args.sigma),
            noise=args.noise,
            outliers="keep" if args.keep_outliers else "set_aside",
            prior=prior,
            frame_drift=args.frame_drift,
        )
        check_physical(cal)  # before anything is written
    except ValueError as e:
        raise UsageError(f"{args.data}: {e}") from None
    data = cal.data  # as fitted: rows set aside, stops read several times merged
    post = bands = None
    if args.mcmc:
        post = posterior(st, cal, n_steps=args.steps, seed=0, progress=True)
        bands = predictive_bands(st, post, plan_x_line(), n_samples=100)
    try:
        structure, no_test = structure_test(cal, st), None
    except TooFewRowsError as e:  # a fit of a few stops is still a fit
        structure, no_test = None, f"structure test not run: {e}"
    paths = write_calibration_report(
        table,
        st,
        cal,
        data,
        args.out,
        str(args.data),
        posterior=post,
        bands=bands,
        structure=structure,
    )
    print(cal.report())
    print(structure.words() if structure is not None else no_test)
    print(f"wrote {', '.join(str(p) for p in paths)}", file=sys.stderr)
    return 0


def _fitted_model_note(path, table) -> str:
    """What `calibrate` takes of a fitted model file given as its table: its table and the
    table's hardware effects, its zero lengths as the controller's. The file's fitted
    effects and its `[controller]` zero lengths (`validate`'s rule) are not used: say so."""
    import numpy as np

    from ._calibration.model_file import load_fitted_model
    from ._effects import default_effects

    model = load_fitted_model(path)
    fitted = [n for n in (model.effects or {}) if n not in default_effects(table)]
    moved = model.nominal_zero_lengths is not None and not np.allclose(
        model.nominal_zero_lengths, table.zero_lengths, rtol=0, atol=1e-9
    )
    if not (fitted or moved):
        return ""
    parts = []
    if fitted:
        parts.append(f"its fitted effects ({', '.join(fitted)}) are not in this fit")
    if moved:
        parts.append(
            "commanded lengths convert with its fitted zero lengths (a controller loaded with "
            "the fitted table), not with its [controller] ones as validate does (a controller "
            "still on its nominal table)"
        )
    return (
        f"note: {path} is a fitted model: calibrate fits its table with the table's hardware "
        f"effects; {'; '.join(parts)}. Where the controller still runs the nominal table, "
        "calibrate from that table"
    )


def _diagnose(args) -> int:
    from ._calibration.fit import check_physical
    from ._calibration.measurements import load_measurements
    from ._calibration.outliers import repeat_words
    from ._discovery.diagnose import diagnose, group_label
    from ._effects import EFFECTS
    from ._reports.diagnose import write_report

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
    base = _names(args.base, "--base")
    library = _names(args.effects, "--effects") or tuple(EFFECTS)
    for name in base + library:
        if name not in EFFECTS:
            raise UsageError(f"unknown effect '{name}'; known: {', '.join(EFFECTS)}")
    out = Path(args.out)
    json_path = Path(args.json) if args.json else out / "diagnosis.json"
    try:
        with warnings.catch_warnings():  # a table that is not physical: refused below
            warnings.filterwarnings("ignore", "the fitted table is not physical", RuntimeWarning)
            diag = diagnose(
                table,
                data,
                base=base,
                library=library,
                compensated=args.compensated,
                alpha=args.alpha,
                noise=args.noise,
                sigma=_sigma_arg(args.sigma),
                folds=args.folds,
                outliers="keep" if args.keep_outliers else "set_aside",
                session_steps="keep" if args.keep_sessions else "split",
            )
        check_physical(diag.final)  # before anything is written
    except ValueError as e:
        raise UsageError(f"{source}: {e}") from None
    paths = write_report(diag, out, source, json_path)
    if diag.repeated:
        print(repeat_words(diag.repeated))
    if diag.set_aside:
        print(
            f"{len(diag.set_aside)} reading(s) set aside as gross errors: "
            + "; ".join(g.words() for g in diag.set_aside)
        )
    for split in diag.split_sessions:
        print(split.words())
    print(
        f"selected: {', '.join(map(form_label, diag.selected_forms)) or 'none'}; unexplained: "
        f"{str(diag.unexplained).lower()}; RMS {diag.rms_before:.3f} -> {diag.rms_after:.3f} "
        f"sigma, held-out {heldout_text(diag.heldout_rms_before)} -> "
        f"{heldout_text(diag.heldout_rms_after, suffix=' sigma')}"
    )
    if not math.isfinite(diag.heldout_rms_after):
        print(
            f"held-out check not defined: {UNDEFINED_WORDS}; no effect can be accepted without it"
        )
    if diag.instrument_scale is not None:
        print(diag.instrument_scale.words())
    if diag.instrument_drift is not None:
        print(diag.instrument_drift.words())
    for f in diag.discovered:
        print(f"discovered: {f.words}")
    if diag.absorbed:
        print(f"absorbed (the model already reproduces them here): {', '.join(diag.absorbed)}")
    for group, plan in zip(diag.ambiguous, diag.plans):
        print(
            "ambiguous: "
            + " / ".join(group_label(c) for c in group)
            + (f"; {plan['plan']}: " if plan["plan"] else "; ")
            + plan["plan_words"]
        )
    if diag.structure is not None:
        print(diag.structure.words())
    if diag.residual_model is not None:
        gp = diag.residual_model
        print(
            f"a GP residual model{gp.scope()} gains {100 * gp.gain:.1f} % on held-out rows; "
            f"it depends most on: {'; '.join(gp.hints()[:4])}"
        )
    print(f"wrote {json_path} and {', '.join(str(p) for p in paths)}", file=sys.stderr)
    return 0


def _validate(args) -> int:
    import warnings

    from ._calibration.measurements import load_measurements
    from ._calibration.model_file import load_fitted_model
    from ._calibration.outliers import repeat_words
    from ._calibration.validate import validate_model
    from ._reports.validate import write_validation_report

    model = load_fitted_model(args.model)
    data = load_measurements(args.data)
    nominal = None if args.table is None else _table(args.table)
    print(f"predicting {len(data)} rows of {args.data} with {args.model} ...", file=sys.stderr)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the report says "fit" in words
            v = validate_model(
                model,
                data,
                register=args.register,
                compensated=args.compensated,
                nominal=nominal,
                frame_drift=args.frame_drift,
            )
    except ValueError as e:
        raise UsageError(f"{args.data}: {e}") from None
    out = Path(args.out)
    json_path = Path(args.json) if args.json else out / "validation.json"
    paths = write_validation_report(v, out, str(args.model), str(args.data), json_path)
    kind = "prediction" if v.is_prediction else "FIT, not a prediction: every row registered"
    unit = "rows" if v.stops is None else "stops"
    means = "" if v.stops is None else " (a stop read several times: the mean of its readings)"
    print(
        f"{kind}: {v.rows_predicted} {unit} predicted, {v.rows_registered} registered{means}; "
        "RMS "
        + ", ".join(f"{c} {r:.4g}" for c, r in v.rms.items())
        + ("" if v.leg_rms is None else f"; legs {v.leg_rms:.4g} mm")
    )
    if v.repeated:
        print(repeat_words(v.repeated))
    if v.set_aside:
        print(
            f"{len(v.set_aside)} reading(s) no table could have produced set aside: "
            + "; ".join(g.words() for g in v.set_aside[:5])
            + ("; ..." if len(v.set_aside) > 5 else "")
        )
    if args.frame_drift and not v.rows_registered:
        from ._calibration.validate import NO_NEW_SESSION

        print(f"note: {NO_NEW_SESSION}", file=sys.stderr)
    for line in v.drift_lines() + v.trend_lines():
        print(line)
    if v.noise_ratio:
        print(v.noise_words())
    print(f"wrote {', '.join(str(p) for p in paths)}", file=sys.stderr)
    return 0


def _design_inputs(args):
    """(design, workspace, text) from --table, --workspace, --leg-stiffness, --payload."""
    from ._analysis.workspaces import Workspace, load_workspace
    from ._design.evaluate import as_design
    from ._design.hardware import hardware_for
    from ._io import load_model, reference_table

    if args.table is None:
        table, effects = reference_table(), None
    else:
        table, effects = load_model(args.table)
    options = {"effects": effects, "payload": args.payload}
    if args.leg_stiffness is not None:
        options["leg_stiffness"] = args.leg_stiffness
    design = as_design(table, hardware_for(table, **options))
    if args.workspace is None:
        ws = Workspace()
        return design, ws, ws.describe()
    ws = load_workspace(args.workspace)
    text = ws.describe() if isinstance(ws, Workspace) else f"{len(ws)} poses from {args.workspace}"
    return design, ws, text


def _design_evaluate(args) -> int:
    from ._design.evaluate import assess
    from ._reports.design import write_evaluation_report

    design, ws, text = _design_inputs(args)
    print(f"evaluating '{design.table().name}' over {text} ...", file=sys.stderr)
    a = assess(design, workspace=ws, n_sweep=args.n_sweep, n_random=args.n_random)
    out = Path(args.out)
    json_path = Path(args.json) if args.json else out / "design.json"
    from ._analysis.workspaces import Workspace

    n_sweep = args.n_sweep if isinstance(ws, Workspace) else None
    print(write_evaluation_report(a, out, text, n_sweep, json_path))
    print(f"wrote {out / 'design.md'}, {json_path}", file=sys.stderr)
    return 0


def _parse_bounds(text: str) -> dict:
    """'base_radius=500:900,base_half_angle=2:30' (file units) -> {name: (lo, hi)} raw."""
    out = {}
    for item in filter(None, (t.strip() for t in text.split(","))):
        name, _, rng = item.partition("=")
        lo, sep, hi = rng.partition(":")
        try:
            out[name.strip()] = (float(lo), float(hi))
        except ValueError:
            raise UsageError(f"--bounds: '{item}' is not NAME=LO:HI") from None
        if not sep:
            raise UsageError(f"--bounds: '{item}' is not NAME=LO:HI")
    return out


def _design_optimize(args) -> int:
    import math

    from ._design.optimize import optimize_design, pareto_front, parse_constraint
    from ._design.symmetric import SymmetricDesign
    from ._design.variables import ANGLES, Design
    from ._reports.design import write_optimization_report

    design, ws, text = _design_inputs(args)
    vary = list(_names(args.vary, "--vary"))
    if not args.as_table:
        try:
            design = Design(SymmetricDesign.from_table(design.table()), design.hardware)
        except TableFileError as e:
            if any(
                v in SymmetricDesign.__dataclass_fields__
                and v not in design.table().__dataclass_fields__
                for v in vary
            ):
                raise
            print(f"note: {e}; varying table leaves", file=sys.stderr)
    try:
        constraints = [parse_constraint(c) for c in args.constraint]
        bounds = {
            n: tuple(math.radians(x) if n in ANGLES else x for x in b)
            for n, b in _parse_bounds(args.bounds).items()
        }
        catalogue = (
            [float(x) for x in args.lead_catalogue.split(",")] if args.lead_catalogue else None
        )
        options = dict(
            workspace=ws,
            bounds=bounds,
            lead_catalogue=catalogue,
            starts=args.starts,
            seed=args.seed,
            progress=True,
        )
        front = None
        if args.pareto:
            front = pareto_front(
                design,
                vary,
                args.objective,
                args.pareto,
                constraints,
                n_points=args.pareto_points,
                **options,
            )
            r = front.ends[0]
        else:
            r = optimize_design(design, vary, args.objective, constraints, **options)
    except ValueError as e:
        if isinstance(e, TableFileError):
            raise
        raise UsageError(str(e)) from None
    out = Path(args.out)
    json_path = Path(args.json) if args.json else out / "design_optimize.json"
    print(write_optimization_report(r, out, json_path, front))
    print(
        f"wrote {out / 'design_optimize.md'}, {out / 'design.toml'}, {json_path}", file=sys.stderr
    )
    return 0


def _bench(args) -> int:
    # The benchmark and its numpy/scipy baselines live in the source checkout's benchmarks/
    # (the installed library carries one kinematics only).
    root = Path(__file__).resolve().parents[1]
    if not (root / "benchmarks" / "bench.py").exists():
        raise UsageError(
            "the benchmark lives in the source checkout (benchmarks/); run `python -m "
            "benchmarks` from a clone of the repository"
        )
    sys.path.insert(0, str(root))
    from benchmarks.__main__ import main as bench_main

    argv = ["--out", str(args.out)] + (["--quick"] if args.quick else [])
    argv += ["--suite"] if args.suite else []
    if args.table is not None:
        argv += ["--table", str(args.table)]
    return bench_main(argv)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="jaxtable", description=__doc__)
    p.add_argument(
        "--no-cache",
        action="store_true",
        help="do not use the persistent compilation cache (default: on, in "
        "$JAXTABLE_CACHE_DIR or ~/.cache/jaxtable/jax; a repeat run on data of the same shape "
        "skips most compilation)",
    )
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

    def noise_options(sp, default):
        sp.add_argument(
            "--sigma",
            default=None,
            help="state the measurement σ: 'x=0.01,roll=2arcsec' (bare numbers: mm, deg; "
            "units mm, um, deg, arcsec, rad; xyz= / angles= for a group) or an instrument "
            "preset (tracker6, point3, interferometer); overrides the file's sigma_ columns",
        )
        sp.add_argument(
            "--noise",
            choices=["estimate", "fixed"],
            default=default,
            help="estimate (default): σ of each column group estimated from the fit (a "
            "stated σ sets relative weights and is tested against it); fixed: trust the "
            "stated σ",
        )

    def outlier_options(sp):
        sp.add_argument(
            "--keep-outliers",
            action="store_true",
            help="fit every reading (default: rows that repeat an earlier row to the last "
            "digit and readings no table could have produced are set aside before any fit; "
            "readings the fit cannot reconcile with the rest are found by data snooping with "
            "a robust scale, family-wise false-alarm rate 1 %%; all named in the report)",
        )

    def compensation(sp, default=None, what="without cmd_l columns: the controller"):
        """--compensated / --uncompensated, the same pair in every verb (DESIGN.md: without
        cmd_l columns on a table with a lead, the user must say which)."""
        g = sp.add_mutually_exclusive_group()
        g.add_argument(
            "--compensated",
            dest="compensated",
            action="store_const",
            const=True,
            default=default,
            help=f"{what} compensated the passive spiral term"
            + (" (default)" if default is True else ""),
        )
        g.add_argument(
            "--uncompensated",
            dest="compensated",
            action="store_const",
            const=False,
            help=f"{what} did not compensate the passive spiral term",
        )

    sp = sub.add_parser(
        "spiral",
        help="passive spiral term: Fig. 5/6 re-drawn, pose error "
        "with and without compensation along x and over the workspace",
    )
    common(sp, "out/spiral")
    sp.add_argument(
        "--samples",
        type=_whole(1),
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
    sp.add_argument("--n", type=_whole(2), default=101, help="points per slice axis (default 101)")
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
    sp.add_argument("--n", type=_whole(1), default=100, help="poses (random, swing)")
    sp.add_argument("--seed", type=_whole(0), default=0)
    sp.add_argument("--joint-sigma", type=_number(0.0), default=0.010, help="mm (default 0.010)")
    sp.add_argument("--zero-sigma", type=_number(0.0), default=0.050, help="mm (default 0.050)")
    sp.add_argument("--frame", default="", help="instrument frame, e.g. 'x=50,yaw=2' (mm, deg)")
    sp.add_argument("--target", default="", help="target on the platform, e.g. 'z=80'")
    compensation(sp, default=True, what="the simulated controller")
    sp.set_defaults(func=_simulate)

    sp = sub.add_parser(
        "calibrate",
        help="fit parameters to a measurement CSV (Gauss–Newton), with "
        "covariance and an identifiability report",
    )
    sp.add_argument("data", type=Path, help="measurement CSV")
    common(sp, "out/calibrate")
    sp.add_argument(
        "--free",
        default=",".join(GEOMETRY),
        help="comma-separated free parameters (table leaves or effect.field, e.g. spiral.lead; "
        "spiral.lead[all]: one value for all legs)",
    )
    sp.add_argument(
        "--no-frame",
        action="store_true",
        help="data are in the base frame: do not estimate the instrument frame",
    )
    sp.add_argument(
        "--frame-drift",
        action="store_true",
        help="the instrument's frame drifts over each session (a tracker or its stand "
        "warming up): fit a linear drift of it in the file's time as a nuisance beside the "
        "frame (diagnose says when the data prefer it to a drift of the legs)",
    )
    compensation(sp)
    noise_options(sp, "estimate")
    outlier_options(sp)
    sp.add_argument(
        "--prior",
        default=None,
        metavar="paper|FILE",
        help="a Gaussian prior on the geometry from a tolerance budget ('paper': the "
        "paper's; FILE: a tolerance file, as for `map`): the fit is then the maximum a "
        "posteriori one, what the data cannot determine stays within its tolerance, and the "
        "report says what the data determine (default: no prior)",
    )
    sp.add_argument(
        "--mcmc",
        action="store_true",
        help="also sample the posterior with emcee (corner plot, predictive bands)",
    )
    sp.add_argument("--steps", type=_whole(1), default=2000, help="emcee steps per walker (2000)")
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
    compensation(sp)
    noise_options(sp, "estimate")
    outlier_options(sp)
    sp.add_argument(
        "--keep-sessions",
        action="store_true",
        help="keep the file's sessions (default: where structure is left unexplained, a "
        "step in time within a session, the instrument or the legs' zeros moved part-way, "
        "makes the rows after it a new session, named in the report)",
    )
    sp.add_argument(
        "--alpha",
        type=_number(0.0, above=True, below=1.0),
        default=0.01,
        help="false-alarm rate of the structure test (0.01; it does not depend on σ's scale)",
    )
    sp.add_argument("--folds", type=_whole(2), default=5, help="k of the k-fold held-out score (5)")
    sp.set_defaults(func=_diagnose)

    sp = sub.add_parser(
        "validate",
        help="predict measured data with a fitted model file (calibrated_table.toml): stored "
        "frames for known sessions, a new session's frame registered on its first N stops",
    )
    sp.add_argument("model", type=Path, help="fitted model file (calibrate / diagnose --out)")
    sp.add_argument("data", type=Path, help="measurement CSV")
    common(sp, "out/validate")
    sp.set_defaults(table=None)
    sp.add_argument(
        "--register",
        type=_whole(1),
        default=None,
        help="stops at the start of each new session that register its frame (a row a "
        "stop; consecutive rows of one command, a stop read several times, count once); the "
        "rest are predicted (default: all rows, which makes the result a fit, not a "
        "prediction)",
    )
    sp.add_argument(
        "--frame-drift",
        action="store_true",
        help="a new session's instrument frame drifts over the session (a tracker or its "
        "stand warming up): register a linear drift of it in the file's time with the "
        "frame, on the --register stops spread evenly over the session (first and last "
        "among them) instead of its first ones; stored frames are used as stored",
    )
    sp.add_argument("--json", default=None, help="JSON result (default: OUT/validation.json)")
    compensation(sp)
    sp.set_defaults(func=_validate)

    sp = sub.add_parser(
        "design",
        help="design trade studies: evaluate a table over a required workspace (coverage, "
        "dexterity, accuracy, stiffness, actuator duty, first frequency) or optimise it",
    )
    dsub = sp.add_subparsers(dest="design_verb", required=True)

    def design_common(dp, out_default):
        common(dp, out_default)
        dp.add_argument(
            "--workspace",
            type=Path,
            default=None,
            help="required workspace: TOML (single = [6], combined = [6], mm / deg) or a CSV "
            "pose list (x..yaw); default: the reference table's",
        )
        dp.add_argument(
            "--leg-stiffness",
            type=_number(0.0, above=True),
            default=None,
            help="axial leg stiffness, N/mm (default: the model's compliance effect, else 2e4)",
        )
        dp.add_argument("--payload", type=_number(0.0), default=100.0, help="kg (default 100)")
        dp.add_argument("--json", default=None, help="JSON result (default: in OUT)")

    dp = dsub.add_parser("evaluate", help="every design criterion over the workspace")
    design_common(dp, "out/design")
    dp.add_argument(
        "--n-sweep", type=_whole(2), default=11, help="points per single-DOF sweep (11)"
    )
    dp.add_argument("--n-random", type=_whole(0), default=256, help="random box poses (256)")
    dp.set_defaults(func=_design_evaluate)

    dp = dsub.add_parser(
        "optimize",
        help="optimise one criterion over design variables by gradient (several starts; "
        "hand and a lead catalogue enumerated), with constraints and a Pareto front",
    )
    design_common(dp, "out/design_optimize")
    dp.add_argument(
        "--vary",
        required=True,
        help="comma-separated design variables: base_radius, platform_radius, "
        "base_half_angle, platform_half_angle, home_height, base_axis_offset, "
        "platform_axis_offset, platform_z (symmetric table), lead, hand, stroke, "
        "leg_stiffness, tolerances.SOURCE, ... (angles in deg)",
    )
    dp.add_argument("--objective", required=True, help="criterion to optimise (its sense is known)")
    dp.add_argument(
        "--constraint",
        action="append",
        default=[],
        help="NAME<=V or NAME>=V on a criterion (repeatable)",
    )
    dp.add_argument("--bounds", default="", help="NAME=LO:HI,... (file units; default ±50 %%)")
    dp.add_argument(
        "--lead-catalogue", default=None, help="leads to enumerate, e.g. 5,10,12.7,16,20"
    )
    dp.add_argument("--pareto", default=None, help="second criterion: the Pareto front with it")
    dp.add_argument("--pareto-points", type=_whole(2), default=7, help="ε values on the front (7)")
    dp.add_argument("--starts", type=_whole(1), default=4, help="gradient starts (4)")
    dp.add_argument("--seed", type=_whole(0), default=0)
    dp.add_argument(
        "--as-table",
        action="store_true",
        help="vary the table's own leaves even when it is a symmetric hexapod",
    )
    dp.set_defaults(func=_design_optimize)

    sp = sub.add_parser(
        "bench",
        help="benchmarks with numpy/scipy baselines in the same run: inverse and forward "
        "kinematics, sensitivities, calibration, emcee, single-pose latency, a 1e8-pose map "
        "(without the persistent compilation cache: compile times are first compilations)",
    )
    common(sp, "out/bench")
    sp.add_argument("--quick", action="store_true", help="tiny sizes: a smoke run (~1 min)")
    sp.add_argument(
        "--suite",
        action="store_true",
        help="also time the default test suite from an empty compilation cache (~12 min, 2 cores)",
    )
    sp.set_defaults(func=_bench)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    # the benchmark times first compilations: it never reads the persistent cache (its
    # diagnose rows run child processes on an empty cache, then on that cache warm)
    if not args.no_cache and args.func is not _bench:
        enable_compilation_cache()
    try:
        return args.func(args)
    except (
        TableFileError,
        KinematicsError,
        ToleranceFileError,
        DataFileError,
        WorkspaceFileError,
        UsageError,
    ) as e:
        print(f"jaxtable {args.verb}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
