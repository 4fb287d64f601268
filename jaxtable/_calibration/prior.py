"""A Gaussian prior on a calibration's parameters from the tolerance budget: the table as
built is the nominal one within its tolerances (`Tolerances`), so each geometric parameter
θᵢ (a step from the nominal value) has the prior N(0, σᵢ²), σᵢ from
`tolerances.parameter_sigma`.

The fit then minimises χ² + Σ (θᵢ / σᵢ)², the maximum a posteriori (MAP) estimate: the prior
enters as one pseudo-observation θᵢ / σᵢ per parameter (`weights` = 1 / σᵢ), so the fit's
covariance is the posterior's, (JᵀJ + Λ)⁻¹ with Λ = diag(1 / σᵢ²), and every combination the
data do not determine stays within its tolerance instead of drifting (on an x line alone,
without the prior, joints moved by 200 mm with σ = inf). What the data determine shows as a
posterior σ well below the prior's (`Calibration.prior_share`).

Joint sets fitted modulo rigid motions have their coordinates in an orthonormal basis of
the non-rigid displacements (`fit.complement_basis`): N(0, σ² I) on the 18 coordinates
projects to N(0, σ² I) on the 12 basis coordinates, so the same σ applies. Instrument
frames, the target offset and the other effects' fields have no prior (weight 0)."""

import numpy as np

from .._analysis.tolerances import Tolerances, parameter_sigma
from .._distributions import chi2_sf


def parameter_of(key: str) -> str:
    """The model parameter of a flat key: `base_joints.g7` -> `base_joints`,
    `zero_lengths[3]` -> `zero_lengths`, `spiral.lead[all]` -> `spiral.lead`."""
    head = key.partition("[")[0]
    for joints in ("base_joints", "platform_joints"):
        if head.startswith(joints + ".g"):
            return joints
    return head


def weights(names, tol: Tolerances | None) -> np.ndarray:
    """(P,) 1 / σ of the prior on each flat parameter `names` (`Setup.names`), 0 where the
    budget says nothing (frames, target, effects other than the lead and spiral lead) or
    `tol` is None. A source with σ = 0 would pin its parameters: refused."""
    out = np.zeros(len(names))
    if tol is None:
        return out
    if not isinstance(tol, Tolerances):
        raise TypeError(f"prior must be a Tolerances (or None), got {type(tol).__name__}")
    sigma = parameter_sigma(tol)
    for i, key in enumerate(names):  # a loop over parameter names, not over data
        s = sigma.get(parameter_of(key))
        if s is None:
            continue
        if not s > 0:
            raise ValueError(
                f"prior: the tolerance of {parameter_of(key)} is 0, which would pin "
                f"{key} to its nominal value; leave it out of `free` instead"
            )
        out[i] = 1.0 / s
    return out


def check(value, covariance, prior_sigma) -> tuple[float, float, float]:
    """Whether a MAP fit's table is within its tolerances: (X, expected, p) with
    X = Σ (θᵢ / σᵢ)² over the parameters with a prior (`value` (P,), `prior_sigma` (P,),
    inf where none), its expected value were the table drawn from the prior, and the
    probability of a larger X then.

    Linear-Gaussian: with θ ~ N(0, Σ_p) and the data's information, the estimate has
    covariance Σ_p − Σ_post (`covariance` the fit's), so X is a sum of χ²₁ weighted by the
    eigenvalues λ ∈ [0, 1] of I − W Σ_post W (W = diag(1 / σ)): E X = Σ λ, one per direction
    the data determine. p by Satterthwaite's scaled χ² (mean and variance matched). A small
    p: the data pull the geometry beyond its tolerances (the table is not built to them, or
    the model lacks an effect the geometry absorbs)."""
    sigma = np.asarray(prior_sigma, float)
    on = np.isfinite(sigma)
    w = 1.0 / sigma[on]
    x = float(np.sum((np.asarray(value, float)[on] * w) ** 2))
    C = np.asarray(covariance, float)[np.ix_(on, on)] * np.outer(w, w)
    lam = np.clip(np.linalg.eigvalsh(np.eye(on.sum()) - 0.5 * (C + C.T)), 0.0, 1.0)
    mean, second = float(lam.sum()), float(np.sum(lam**2))
    if second <= 0:
        return x, 0.0, 1.0 if x == 0 else 0.0
    scale, nu = second / mean, mean**2 / second
    return x, mean, float(chi2_sf(x / scale, nu))
