"""Command line: `jaxtable <verb>`. Every verb takes --table FILE (default: the embedded
reference table) and writes its figures and a Markdown report into --out DIR."""

import argparse
import sys
from pathlib import Path

from ._errors import KinematicsError, TableFileError


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
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (TableFileError, KinematicsError) as e:
        print(f"jaxtable {args.verb}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
