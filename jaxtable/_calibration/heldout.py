"""Held-out scores of a fit: k-fold cross-validation from one fit, by the block-deletion
identity of least squares (no refits)."""

import math

import numpy as np
from scipy.linalg import LinAlgError, cho_factor, cho_solve
from scipy.linalg.lapack import dpocon

from .._threads import one_blas_thread
from .fit import Calibration
from .noise import fit_basis


def make_folds(n: int, k: int, seed: int, grouped: bool = False, strata=None) -> list[np.ndarray]:
    """k disjoint folds of row indices 0..n−1 (sorted arrays), rows dealt at random; with
    `grouped`, k contiguous blocks of rows instead (each fold a stretch of the run, so a
    held-out score also tests extrapolation in time and between neighbouring stops).

    `strata` (n,) labels (the session of each row): rows are dealt stratum by stratum, in
    random order within each, to consecutive folds, so a stratum of m rows spreads over
    min(m, k) folds. A session's own parameters (its tracker frame) are then fitted from
    rows outside any fold wherever the session has two rows or more: dealt as one deck, a
    short session could land in one fold, whose held-out residuals the other rows could not
    predict (`heldout_rms` NaN). One stratum deals as without."""
    if grouped:
        return [np.asarray(b) for b in np.array_split(np.arange(n), k)]
    perm = np.random.default_rng(seed).permutation(n)
    if strata is not None:
        perm = perm[np.argsort(np.asarray(strata)[perm], kind="stable")]
    return [np.sort(perm[i::k]) for i in range(k)]


UNDETERMINED = 1e-10
"""`heldout_rms` is NaN when, for some fold, the other rows carry less than this share of the
information on some fitted direction (the reciprocal condition number of G = U_RᵀU_R, whose
eigenvalues lie between 0 and 1): that fold's rows alone determine the direction, so a fit
to the rest leaves it free and the held-out residuals are not defined by the data."""


@one_blas_thread
def heldout_rms(
    cal: Calibration, folds: list, mask: np.ndarray, tol: float = 1e-6, rescale=None
) -> float:
    """k-fold held-out RMS of σ-normalised residuals (pooled over folds): for each fold F,
    the residuals of F's rows under the model fitted to the other rows.

    Computed from the full-data fit by the block-deletion identity of least squares,
    e_F(without F) = (I − H_FF)⁻¹ e_F, H = J (JᵀJ)⁺ Jᵀ, on the Gauss-Newton linearisation at
    the fit (the tests compare it with refits: the corrections are µm-level, where the model
    is linear to many digits). k refits cost k full fits; this costs one SVD. `rescale`
    (N, 6): factors applied to the held-out residuals (to express them in another fit's σ).

    With U an orthonormal basis of J's columns (r of them), H_FF = U_F U_Fᵀ, and the
    m × m solve is done in r dimensions (Woodbury): (I − U_F U_Fᵀ)⁻¹ e_F =
    e_F + U_F G⁻¹ U_Fᵀ e_F, G = I − U_FᵀU_F = U_RᵀU_R over the other rows R (formed from
    them, not by the subtraction): O(m r²), not O(m³) (a 10,000-stop run's folds hold
    12,000 readings).

    NaN where some fold's rows alone determine a fitted direction (`UNDETERMINED`): too few
    stops for k folds (8 stops of a 6-D tracker for 42 geometric parameters), or a fold
    that alone moves some way (the only stops of one direction of travel on an x line).
    """
    e = cal.residual.reshape(-1)
    U = fit_basis(cal.jacobian, tol)
    sq, count = 0.0, 0
    for rows in folds:
        idx = (rows[:, None] * 6 + np.arange(6)[None, :])[mask[rows]]
        UF = U[idx]
        rest = np.ones(len(U), bool)
        rest[idx] = False
        factor = _factor(U[rest])
        if factor is None:
            return math.nan
        x = e[idx] + UF @ cho_solve(factor, UF.T @ e[idx])
        if rescale is not None:  # (N, 6) factors: the residuals in other σ units
            x = x * np.asarray(rescale).reshape(-1)[idx]
        sq += float(x @ x)
        count += len(idx)
    return math.sqrt(sq / max(count, 1))


def _factor(UR):
    """Cholesky factor of G = U_RᵀU_R (r × r), or None where G is singular to
    `UNDETERMINED` (LAPACK's condition estimate from the factor, O(r²))."""
    G = UR.T @ UR
    try:
        c, lower = cho_factor(G)
    except LinAlgError:
        return None
    rcond, info = dpocon(c, float(np.abs(G).sum(0).max()), uplo="L" if lower else "U")
    return (c, lower) if info == 0 and rcond >= UNDETERMINED else None


UNDEFINED_WORDS = (
    "some fold's rows alone determine a fitted parameter (too few stops for "
    "the model, or stops that do not spread over the workspace)"
)


def heldout_text(x: float, spec: str = ".3f", suffix: str = "") -> str:
    """A held-out figure for reports: `x` formatted, or "n/a" where it is NaN
    (`heldout_rms`: not defined by the data)."""
    return f"{x:{spec}}{suffix}" if math.isfinite(x) else "n/a"
