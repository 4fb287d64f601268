"""What a fitted effect is indistinguishable from outside the table.

A lead error common to all six screws, ε, is exactly what an instrument whose positions
read (1 + ε) times the true ones gives: scale the table's joints, its home lengths and
height and the spiral lead by (1 + ε) and every leg length is (1 + ε) times as long
(`tests/test_aliases.py` shows it to 1e-9 mm), which a length
(1 + ε) L0 + (1 + ε) s is, the zero lengths taking the first part and the lead error the
second; the angles do not change, and the instrument's frame and target take the rest. So
pose data cannot tell a common lead error from the instrument's length scale (a laser
tracker's or interferometer's air or wavelength compensation, a wrong temperature at the
instrument): a tracker 200 ppm long gave `lead_scale` with six ε of 184–202 ppm, ±11–14
ppm each. Unequal legs are the screws' own (an instrument scale cannot make them), but
their mean still could be the instrument's.
"""

from dataclasses import dataclass

import numpy as np

from .._distributions import chi2_sf


@dataclass(frozen=True)
class ScaleAlias:
    """`lead_scale` fitted on every leg, against the instrument's length scale: `eps` the
    legs' common ε (generalised least squares of the six with their covariance) and its
    σ `std`; `equal_legs_p` the χ² test (5 dof) of six equal ε; `agree`: p ≥ the test's α
    (the data do not reject equal legs)."""

    eps: float
    std: float
    equal_legs_p: float
    agree: bool

    def words(self) -> str:
        ppm, sd = 1e6 * self.eps, 1e6 * self.std
        alias = (
            f"an instrument whose positions read {1 + self.eps:.7g} times the true ones "
            f"(its length scale {ppm:+.3g} ppm: a laser tracker's or interferometer's air or "
            "wavelength compensation, a wrong temperature at the instrument), with the "
            "table's size scaled alike"
        )
        if self.agree:
            return (
                f"lead_scale: the six legs' ε agree ({ppm:+.3g} ± {sd:.2g} ppm for all, equal "
                f"legs p = {self.equal_legs_p:.2g}): the same readings as {alias}; pose data "
                "cannot tell the screws' leads from the instrument's scale. Before changing "
                "the controller's leads, check the instrument on a length standard (or the "
                "screws' lead on their own)"
            )
        return (
            f"lead_scale: the legs' ε differ (equal legs p = {self.equal_legs_p:.2g}), which "
            f"an instrument's scale cannot do; their common part ({ppm:+.3g} ± {sd:.2g} ppm) "
            f"gives the same readings as {alias}: pose data cannot tell that part from the "
            "instrument's scale"
        )

    def as_json(self) -> dict:
        return {
            "common_eps": self.eps,
            "std": self.std,
            "equal_legs_p": self.equal_legs_p,
            "legs_agree": self.agree,
            "words": self.words(),
        }


def instrument_scale(cal, mask, alpha: float = 0.01) -> ScaleAlias | None:
    """The `ScaleAlias` of a fit `cal` (a `Calibration`) whose `lead_scale.eps` is fitted
    on all six legs with finite σ, of data whose measured cells `mask` (N, 6) hold
    positions; None otherwise (an angle instrument sees no length scale; one leg's lead
    error is that leg's). `alpha`: the level of the equal-legs test."""
    idx = [cal.names.index(f"lead_scale.eps[{i}]") for i in range(1, 7) if
           f"lead_scale.eps[{i}]" in cal.names]  # fmt: skip
    if len(idx) < 6 or cal.covariance is None or not np.asarray(mask)[:, :3].any():
        return None
    C = np.asarray(cal.covariance, float)[np.ix_(idx, idx)]
    eps = np.asarray(cal.value, float)[idx]
    if not (np.all(np.isfinite(C)) and np.all(np.isfinite(eps)) and np.all(np.diag(C) > 0)):
        return None
    W = np.linalg.pinv(C)
    one = np.ones(6)
    info = float(one @ W @ one)
    if info <= 0:
        return None
    common = float(one @ W @ eps) / info
    dev = eps - common
    stat = float(dev @ W @ dev)
    dof = int(np.linalg.matrix_rank(C)) - 1
    p = float(chi2_sf(stat, dof)) if dof > 0 else 1.0
    return ScaleAlias(common, float(np.sqrt(1.0 / info)), p, p >= alpha)
