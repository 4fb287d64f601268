"""Gross errors in measured data: readings a fit cannot reconcile with the rest (a tracker's
beam broken for one reading, a target re-seated, a value typed into the wrong row).

The test is data snooping with a robust scale, on a model that fits: where the fit's
residuals show structure (`_discovery.structure`), a gross error cannot be told from the
tails of what the model misses, and the callers do not screen (an unmodelled thermal drift
otherwise had readings set aside; a few gross errors do not raise that test: p = 0.76 with
four planted in 80 stops). For every fitted reading i the studentised
residual w_i = e_i / √r_i (e_i the σ-normalised residual, r_i = 1 − H_ii its redundancy
number: the part of an error the fit cannot absorb) is divided by its noise group's robust
scale, 1.4826 × the median |w| over the group (a few gross errors do not inflate it, as they
do the fit's σ). Readings beyond the two-sided normal quantile at α / (2 M) (M tested
readings: a family-wise false-alarm rate α on clean data; Student's t rather than the normal
law, for the scale's own error) are gross errors; per round only the largest (beyond its
bound) is set aside (a gross error pulls the fit, and with it readings that are fine:
a 1 mm error in one x reading moved ten others past the bound), the model is refitted and
the test repeated until none is left. Each is then reported with its residual from the
final model, fitted without it (the whole error, not the part the fit left). Readings with a
redundancy under `MIN_REDUNDANCY` are not tested: the fit absorbs an error there, whatever
its size (the report counts them). A reading far out whose neighbours (in time and in the
legs' extensions) are far out the same way is not a gross error but structure the model
misses, and is kept (`screen`): without that rule an unmodelled thermal drift had 52 of its
readings set aside.
"""

from dataclasses import dataclass, replace
from statistics import NormalDist

import numpy as np

from .._errors import POSE_COLUMNS
from .noise import robust_scales

MIN_REDUNDANCY = 0.05
ALPHA = 0.01
ALONE = 2.5  # mean neighbour z (own direction) below which a reading stands alone
BURST = 5  # the most readings in a row (one column, in time) a gross error may come in
TRIAL_ROUNDS = 10  # gross errors the screen may set aside where the fit shows structure


@dataclass(frozen=True)
class GrossError:
    """One reading set aside: `row` (1 = the first data row), `column` (x … yaw),
    `residual` (measured − model, mm or degrees), `z` (studentised, in robust σ)."""

    row: int
    column: str
    residual: float
    z: float

    def words(self) -> str:
        unit = "mm" if self.column in POSE_COLUMNS[:3] else "°"
        return f"row {self.row} {self.column} {self.residual:+.4g} {unit} ({self.z:+.0f}σ)"


def without(data, cells):
    """`data` (Measurements) with the readings `cells` — (row index, column index) pairs or
    `GrossError`s (1-based rows, column names) — set to not measured (NaN) and marked in
    `aside` (the instrument read them: `noise.noise_model` keeps each row's set of columns);
    a copy."""
    measured = np.array(data.measured, float)
    aside = np.zeros(measured.shape, bool) if data.aside is None else np.array(data.aside, bool)
    for cell in cells:
        if isinstance(cell, GrossError):
            cell = (cell.row - 1, POSE_COLUMNS.index(cell.column))
        measured[cell[0], cell[1]] = np.nan
        aside[cell[0], cell[1]] = True
    return replace(data, measured=measured, aside=aside)


def threshold(tested: int, alpha: float = ALPHA, group: int | None = None) -> float:
    """|z| beyond which a reading is a gross error: the two-sided quantile at α / (2 M) for
    M tested readings, of Student's t with the degrees of freedom of a median-based scale
    from `group` readings (0.37 per reading, the median's efficiency at the normal law; the
    normal law when `group` is None). With the normal quantile, the scale's own error
    (about 8 % from 180 readings) raised the false-alarm rate to 2.2 % (1000 clean data
    sets of 60 stops)."""
    q = 1.0 - alpha / (2.0 * max(tested, 1))
    if group is None:
        return NormalDist().inv_cdf(q)
    from scipy.stats import t

    return float(t.ppf(q, max(0.37 * group, 3.0)))


def screen(cal, mask, groups, extensions, session, alpha: float = ALPHA):
    """The largest gross error of fit `cal` (a `Calibration` with its residuals, weights and
    redundancy numbers) over the fitted readings `mask` (N, 6), noise `groups` (N, 6)
    (−1: none), if any; `extensions` (N, 6) the legs' extensions and `session` (N,) the
    session index of each stop, for its neighbours.

    A reading beyond its bound is a gross error only if it stands alone: in its own
    direction, the mean z of the same column at the stops before and after it (same
    session), and the mean at the three stops nearest in the legs' extensions, are each
    under `ALONE` (each about N(0, 1/2) or N(0, 1/3) beside a true gross error, so 3.5 and
    4.3 sd below it; a gross error pulls them the other way if anything; at 1.5, a planted
    error lost to noise of +1.0σ and +2.3σ at its two stops in time). A model that misses a
    smooth effect (a thermal drift) leaves readings far out whose neighbours are far out
    too: structure, not gross errors, and kept. Gross errors can come in a burst (a
    tracker that lost its beam for three readings: each the others' neighbour, all far
    out): the stops before and after are those past readings beyond their bound the same
    way, at most `BURST` in a row with it (a longer run is structure), and the three stops
    nearest in extensions are those not of its burst and not beyond their bound the same
    way, among its 3 + `BURST` nearest (more of those beyond: structure).

    Returns ((row index, column index, z) or None; readings tested; readings not testable;
    readings beyond their bound that did not stand alone). z is measured − model in robust
    σ."""
    n = mask.shape[0]
    e = np.asarray(cal.residual, float).reshape(n, 6)
    red = np.asarray(cal.redundancy, float).reshape(n, 6)
    fitted = mask & (np.asarray(cal.weight) > 0)
    testable = fitted & (red >= MIN_REDUNDANCY)
    w = np.where(testable, e / np.sqrt(np.where(testable, red, 1.0)), 0.0)
    z = np.zeros_like(w)
    bound = np.full(w.shape, np.inf)
    tested = int(testable.sum())
    labels = np.unique(groups[testable])
    scales = robust_scales(e, red, groups, testable, int(labels.max(initial=-1)) + 1, min_red=0.0)
    for g in labels:
        cells = testable & (groups == g)
        scale = scales[g]
        if scale > 0:
            z[cells] = w[cells] / scale
            bound[cells] = threshold(tested, alpha, int(cells.sum()))
    untested = int((fitted & ~testable).sum())
    far = np.argwhere(np.abs(z) > bound)
    far = far[np.argsort(-(np.abs(z) - bound)[far[:, 0], far[:, 1]])]
    x = np.asarray(extensions, float)
    x = (x - x.mean(0)) / np.where(x.std() > 0, x.std(), 1.0)
    session = np.asarray(session)
    crowded = 0
    for r, c in far:
        # the readings next to it in time, past a burst of at most BURST readings beyond
        # their bound the same way (a beam lost for several readings: each other's
        # neighbours, and all far out)
        beyond = testable[:, c] & (np.sign(z[r, c]) * z[:, c] > bound[:, c])
        side, burst = [], [r]
        for step in (-1, 1):
            k, run = r + step, []
            while 0 <= k < n and session[k] == session[r]:
                if testable[k, c] and not beyond[k]:
                    side.append(k)
                    break
                if testable[k, c]:
                    run.append(k)
                    if len(run) >= BURST:
                        break
                k += step
            burst += run
        # the three stops nearest in the legs' extensions, past at most BURST beyond their
        # bound the same way (gross errors at stops close in extension)
        others = np.flatnonzero(testable[:, c])
        others = others[~np.isin(others, burst)]
        others = others[np.argsort(np.sum((x[others] - x[r]) ** 2, axis=1))]
        nearest = others[: 3 + BURST]
        near = nearest[~beyond[nearest]][:3]
        # a long run or a crowd far out the same way: structure
        long = len(burst) > BURST or beyond[nearest].sum() > BURST
        if long or any(
            len(nb) and np.mean(np.sign(z[r, c]) * z[nb, c]) >= ALONE for nb in (near, side)
        ):
            crowded += 1
            continue
        # residual = model − measured; z as measured − model
        return (int(r), int(c), -float(z[r, c])), tested, untested, crowded
    return None, tested, untested, crowded
