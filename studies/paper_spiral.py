"""The paper's Fig. 5 and 6 re-drawn for the reference table, and the pose error the passive
spiral term causes with and without compensation, along x and over the workspace.

Run:  python studies/paper_spiral.py [--quick] [--out DIR]
      (writes spiral.md and spiral_*.png into DIR, default results/)
"""

import argparse
import time
from pathlib import Path

import jaxtable as jt

RESULTS = Path(__file__).resolve().parents[1] / "results"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="500 random box poses instead of 20000")
    ap.add_argument("--out", type=Path, default=RESULTS, help="output folder (default results/)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    text = jt.reports.spiral_report(
        jt.reference_table(), args.out, n_random=500 if args.quick else 20000
    )
    print(text)
    print(f"\nwrote {args.out / 'spiral.md'} and figures in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
