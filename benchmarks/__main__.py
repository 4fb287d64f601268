"""`python -m benchmarks [--quick] [--suite] [--out DIR]` from the repository root (same as
`jaxtable bench`): runs the benchmark, prints the Markdown table, writes benchmark.{json,md}
into DIR (default results/). `--suite` also times the default test suite from an empty
compilation cache."""

import argparse
import sys
from pathlib import Path

import jaxtable as jt

from .bench import markdown, run_benchmark, suite_wall, write


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__)
    p.add_argument("--quick", action="store_true", help="tiny sizes: a smoke run (~1 min)")
    p.add_argument(
        "--suite",
        action="store_true",
        help="also time the default test suite from an empty compilation cache (~12 min, 2 cores)",
    )
    p.add_argument("--table", type=Path, default=None, help="table file (default: reference)")
    p.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "results")
    args = p.parse_args(argv)
    table = jt.reference_table() if args.table is None else jt.load_table(args.table)

    def log(message):
        print(message, file=sys.stderr)

    r = run_benchmark(table, quick=args.quick, log=log)
    if args.suite:
        log("default test suite (empty compilation cache) ...")
        r["suite"] = suite_wall()
        log(f"suite: {r['suite']['seconds'] / 60:.1f} min, {r['suite']}")
    print(markdown(r))
    paths = write(r, args.out)
    print(f"wrote {', '.join(str(p) for p in paths)}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
