"""Figures of a posterior: corner plot of the samples, posterior-predictive pose-error bands."""

import numpy as np

from .. import _params as vocab
from .._calibration.posterior import PosteriorResult, PredictiveBands
from .._errors import POSE_COLUMNS
from .._rotation import ARCSEC_PER_RAD
from .figures import pyplot


def _pick(result: PosteriorResult, max_params: int, params) -> list[int]:
    names = result.names
    if params is not None:
        bad = [p for p in params if p not in names]
        if bad:
            raise ValueError(f"unknown parameter(s) {bad}; known: {names}")
        return [names.index(p) for p in params]
    if len(names) <= max_params:
        return list(range(len(names)))
    x = result.samples
    sd = x.std(0)
    ok = sd > 0
    c = np.zeros((len(names), len(names)))
    c[np.ix_(ok, ok)] = np.corrcoef(x[:, ok].T)
    np.fill_diagonal(c, 0.0)
    score = np.abs(c).max(1)
    return sorted(np.argsort(-score, kind="stable")[:max_params].tolist())


def corner_plot(result: PosteriorResult, path, max_params: int = 8, params=None, dpi: int = 80):
    """Write a corner plot (PNG) of the posterior samples: histograms on the diagonal, with
    the LM Gaussian N(value, std²) drawn over them, 2-D histograms below. Shows `params`
    (names) or, when there are more than `max_params` parameters, the `max_params` most
    correlated ones (largest |correlation| with another parameter). Returns the names shown.
    """
    plt = pyplot()

    shown = [vocab.short_label(s) for s in (result.labels or result.names)]
    idx = _pick(result, max_params, params)
    k = len(idx)
    x = result.samples[:, idx]
    size = max(4.0, 1.5 * k)
    fig, axes = plt.subplots(k, k, figsize=(size, size), squeeze=False)
    for i in range(k):
        for j in range(k):
            ax = axes[i, j]
            if j > i:
                ax.set_axis_off()
                continue
            if i == j:
                ax.hist(x[:, i], bins=30, density=True, color="0.6")
                m, s = result.lm_value[idx[i]], result.lm_std[idx[i]]
                if np.isfinite(s) and s > 0:
                    g = np.linspace(x[:, i].min(), x[:, i].max(), 100)
                    ax.plot(g, np.exp(-0.5 * ((g - m) / s) ** 2) / (s * np.sqrt(2 * np.pi)), "r")
                ax.set_yticks([])
            else:
                ax.hist2d(x[:, j], x[:, i], bins=30, cmap="Greys")
            if i == k - 1:
                ax.set_xlabel(shown[idx[j]], fontsize=7)
            else:
                ax.set_xticklabels([])
            if j == 0 and i > 0:
                ax.set_ylabel(shown[idx[i]], fontsize=7)
            elif j > 0:
                ax.set_yticklabels([])
            ax.tick_params(labelsize=6)
    fig.suptitle("posterior (grey) and LM Gaussian (red)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return [result.names[i] for i in idx]


# --- posterior predictive pose error ------------------------------------------------------


def plot_bands(bands: PredictiveBands, path, columns=None, axis: int | None = None, dpi=80):
    """Write a PNG of the predictive bands: one panel per pose column (µm for x, y, z; arcsec
    for angles), the outer percentiles shaded, the median dashed and the LM prediction solid,
    against the commanded coordinate `axis` (default: the pose column that varies most over
    the poses, in mm or deg)."""
    plt = pyplot()

    cols = list(range(6)) if columns is None else [POSE_COLUMNS.index(c) for c in columns]
    p = bands.poses
    if axis is None:
        spread = np.ptp(p, axis=0) * np.array([1, 1, 1, 1e3, 1e3, 1e3])
        axis = int(np.argmax(spread))
    xs = p[:, axis] * (1.0 if axis < 3 else 180 / np.pi)
    order = np.argsort(xs)
    xs = xs[order]
    unit = np.array([1e3] * 3 + [ARCSEC_PER_RAD] * 3)
    fig, axes = plt.subplots(len(cols), 1, figsize=(6, 1.6 * len(cols) + 0.6), sharex=True)
    axes = np.atleast_1d(axes)
    mid = len(bands.percentiles) // 2
    for ax, c in zip(axes, cols):
        b = bands.bands[:, order, c] * unit[c]
        ax.fill_between(xs, b[0], b[-1], color="C0", alpha=0.3, lw=0)
        ax.plot(xs, b[mid], "C0--", lw=1)
        ax.plot(xs, bands.lm[order, c] * unit[c], "k-", lw=1)
        ax.set_ylabel(f"{POSE_COLUMNS[c]} ({'µm' if c < 3 else 'arcsec'})", fontsize=8)
        ax.tick_params(labelsize=7)
    lo, hi = bands.percentiles[0], bands.percentiles[-1]
    axes[0].set_title(
        f"pose error: posterior {lo:g}–{hi:g} % band (shaded), median (dashed), LM (solid)",
        fontsize=8,
    )
    axes[-1].set_xlabel(f"commanded {POSE_COLUMNS[axis]} ({'mm' if axis < 3 else 'deg'})")
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
