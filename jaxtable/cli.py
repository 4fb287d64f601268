"""Command line: `jaxtable <verb>`. Every verb takes --table FILE (default: the embedded
reference table) and writes its figures and a Markdown report into --out DIR."""

import argparse
import sys
from pathlib import Path

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


def _parse_fixed(text: str) -> list[float]:
    from ._errors import POSE_COLUMNS

    fixed = [0.0] * 6
    for item in filter(None, (t.strip() for t in text.split(","))):
        name, _, value = item.partition("=")
        if name not in POSE_COLUMNS:
            raise SystemExit(f"jaxtable map: --fixed: unknown DOF '{name}' in '{item}'")
        try:
            fixed[POSE_COLUMNS.index(name)] = float(value)
        except ValueError:
            raise SystemExit(f"jaxtable map: --fixed: '{item}' is not DOF=number") from None
    return fixed


def _map(args) -> int:
    from ._errormap import error_map, workspace_slice
    from ._map_report import budget_chart, slice_figures, summary_markdown, x_stroke_figure
    from ._tolerance import Tolerances, load_tolerances

    table = _table(args.table)
    tol = Tolerances() if args.tolerances is None else load_tolerances(args.tolerances)
    dofs = tuple(d.strip() for d in args.slice.split(","))
    if len(dofs) != 2:
        raise SystemExit(f"jaxtable map: --slice takes two DOF, e.g. x,y; got '{args.slice}'")
    try:
        grid = workspace_slice(dofs, args.n, fixed=_parse_fixed(args.fixed))
    except ValueError as e:
        raise SystemExit(f"jaxtable map: {e}") from None
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
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (TableFileError, KinematicsError, ToleranceFileError) as e:
        print(f"jaxtable {args.verb}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
