"""Performance of jaxtable against numpy and scipy baselines measured in the same run.

Run:  python studies/benchmark.py [--quick]   (about 6 minutes on 2 cores; writes
      results/benchmark.json and results/benchmark.md; same as `python -m benchmarks` and
      `jaxtable bench --out results`). The benchmark itself lives in `benchmarks/`.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.__main__ import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
