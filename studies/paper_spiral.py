"""The paper's Fig. 5 and 6 re-drawn for the reference table, and the pose error the passive
spiral term causes with and without compensation, along x and over the workspace.

Run:  python studies/paper_spiral.py     (writes results/spiral.md and results/spiral_*.png)
"""

from pathlib import Path

import jaxtable as jt
from jaxtable._spiral_report import spiral_report

if __name__ == "__main__":
    out = Path(__file__).resolve().parents[1] / "results"
    print(spiral_report(jt.reference_table(), out))
