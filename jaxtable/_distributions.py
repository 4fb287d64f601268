"""Tail probabilities and quantiles of the test statistics' laws (χ², F, Student's t), in
numpy on `scipy.special`: the functions scipy.stats' `sf` and `ppf` call for these laws,
without importing scipy.stats (~0.5 s a process, which every fit's noise estimate paid).
Each takes and returns floats or numpy arrays, broadcast."""

import numpy as np
from scipy.special import chdtrc, fdtrc, gammaincinv, stdtr, stdtrit


def chi2_sf(x, dof):
    """P(X > x) for X ~ χ²(dof) (1 for x ≤ 0)."""
    return chdtrc(dof, np.maximum(x, 0.0))  # (scipy.special gives NaN below the support)


def chi2_ppf(q, dof):
    """The q-quantile of χ²(dof)."""
    return 2.0 * gammaincinv(0.5 * dof, q)


def f_sf(x, dof_num, dof_den):
    """P(X > x) for X ~ F(dof_num, dof_den) (1 for x ≤ 0)."""
    return fdtrc(dof_num, dof_den, np.maximum(x, 0.0))


def t_sf(x, dof):
    """P(X > x) for X ~ Student's t(dof)."""
    return stdtr(dof, -x)


def t_ppf(q, dof):
    """The q-quantile of Student's t(dof)."""
    return stdtrit(dof, q)
