"""Report writers: Markdown and figures from library results, the same ones the CLI verbs
write. Public so that studies and users can write any of them from the API:

- `spiral_report(table, out)`: the passive spiral term (`jaxtable spiral`);
- `write_map_report(...)`, `slice_figures`, `x_stroke_figure`, `budget_chart`,
  `summary_markdown`: workspace error maps (`jaxtable map`);
- `write_calibration_report(...)`: fitted table file and report (`jaxtable calibrate`);
- `write_diagnosis_report(diag, out, source, json_path)`, `effect_figures`,
  `signature_figure`: model discovery (`jaxtable diagnose`);
- `corner_plot`, `plot_bands`: posterior figures;
- `pyplot()`: matplotlib with a file-only backend, for a study's own figures.
"""

from ._reports.calibrate import write_calibration_report
from ._reports.diagnose import effect_figures, signature_figure
from ._reports.diagnose import write_report as write_diagnosis_report
from ._reports.errormap import (
    budget_chart,
    slice_figures,
    summary_markdown,
    write_map_report,
    x_stroke_figure,
)
from ._reports.figures import pyplot
from ._reports.posterior import corner_plot, plot_bands
from ._reports.spiral import spiral_report

__all__ = [
    "budget_chart",
    "corner_plot",
    "effect_figures",
    "plot_bands",
    "pyplot",
    "signature_figure",
    "slice_figures",
    "spiral_report",
    "summary_markdown",
    "write_calibration_report",
    "write_diagnosis_report",
    "write_map_report",
    "x_stroke_figure",
]
