"""Performance of jaxtable against numpy and scipy baselines measured in the same run.

Run:  python studies/benchmark.py     (about 6 minutes on 2 cores; writes
      results/benchmark.json and results/benchmark.md; same as `jaxtable bench --out results`)
"""

import sys
from pathlib import Path

import jaxtable as jt
from jaxtable._bench import markdown, run_benchmark, write

if __name__ == "__main__":
    out = Path(__file__).resolve().parents[1] / "results"
    r = run_benchmark(jt.reference_table(), quick="--quick" in sys.argv)
    print(markdown(r))
    write(r, out)
