"""Posterior of a calibration by MCMC (emcee), and what it predicts over the workspace.

The sampled density is the likelihood of the fit, through the exact forward kinematics:

    log p(θ | data) = −½ Σ r(θ)² + log prior(θ)

with r the weighted residuals (reading − measured) / σ of `_calibrate.residual`, over the
parameters the Levenberg-Marquardt fit estimated (table leaves, effect fields, instrument
frames and target). Frozen parameters stay at their fitted values.

Coordinates. The walkers move in the whitened coordinates of the LM solution,
θ = θ_LM + L z, where L Lᵀ is the LM covariance restricted to the identifiable directions
(rank r, z ∈ R^r): the posterior in z is close to N(0, I), so the differential-evolution moves
mix in a few tens of steps whatever the units (mm, rad, mm/rev) and correlations. Directions
the data cannot determine (std = inf in the LM report) are not sampled: they are held at their
LM values and listed in `PosteriorResult.fixed_directions`; a parameter that takes part in one
keeps std = inf in the result (its samples are conditional on the fixed combination).

A set-up with a prior from the tolerances (`setup(..., prior=)`) adds its term,
−½ Σ (θᵢ / σᵢ)², to the log-probability: the sampled posterior is the one the MAP fit
approximates.

Prior. `prior_scale = s` (default 100): a Gaussian N(0, s²) on each whitened coordinate, i.e.
N(θ_LM, s² Σ_LM) on the identifiable subspace: proper, and 100 times wider than the
likelihood, so it changes posterior standard deviations by a factor 1/√(1 + 1/s²) (5e-5 for
s = 100). `prior_scale=None`: flat (improper) prior on the identifiable subspace. Forward
kinematics that fail to converge return the commanded pose, whose residual is large: such
parameter values get a negligible probability rather than NaN; a non-finite log-probability
is mapped to −inf (rejected).
"""

import warnings
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from .._api import actuator_command
from .._errors import KinematicsError, renamed_argument
from .._forward import RESULTS, ForwardOptions, forward_one
from .._jit import jit
from .._rotation import pose_error
from .._threads import one_blas_thread
from .fit import Calibration, Setup, build_model, residual

__all__ = [
    "PosteriorResult",
    "PredictiveBands",
    "posterior",
    "predictive_bands",
]


@dataclass(frozen=True)
class PosteriorResult:
    """Outcome of `posterior`.

    - `names` (P,): the fitted parameters, as `Calibration.names` (keys); `labels` (P,):
      their physical names, as `Calibration.labels`;
    - `samples` (S, P): posterior draws after burn-in and thinning, all walkers pooled, in
      parameter units (mm, rad, mm/rev, ... as `Calibration.value`); `log_prob` (S,);
    - `mean`, `std` (P,): of the samples (std = inf where the parameter takes part in an
      unidentifiable direction, as in the LM report); `lm_value`, `lm_std` (P,): the LM fit;
    - `identifiable` (P,) bool; `fixed_directions`: the LM fit's unidentifiable directions,
      (relative singular value, [(name, weight), ...]) each, held fixed, not sampled;
    - `tau` (r,): integrated autocorrelation time of each whitened coordinate, in steps;
    - `acceptance`: mean acceptance fraction of the walkers;
    - `short_chain`: True when the chain is shorter than 50 τ (a warning was emitted);
    - `n_walkers`, `n_steps`, `burn`, `thin`: the run; `rank` r: sampled dimensions;
    - `theta_lm`, `index`: the LM parameter pytree and the positions of `names` in its flat
      vector (used by `predictive_bands`); `whitening` (P_all, r): L in θ = θ_LM + L z.
    """

    names: list
    samples: np.ndarray
    log_prob: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    lm_value: np.ndarray
    lm_std: np.ndarray
    identifiable: np.ndarray
    fixed_directions: list
    tau: np.ndarray
    acceptance: float
    short_chain: bool
    n_walkers: int
    n_steps: int
    burn: int
    thin: int
    rank: int
    theta_lm: dict = field(repr=False)
    index: np.ndarray = field(repr=False)
    whitening: np.ndarray = field(repr=False)
    labels: list = field(default_factory=list)

    def summary(self) -> str:
        """A markdown table: parameter, LM value ± std, posterior mean ± std, std ratio."""
        lines = [
            f"emcee: {self.n_walkers} walkers × {self.n_steps} steps, burn-in {self.burn}, "
            f"thin {self.thin}, {len(self.samples)} samples; τ max {self.tau.max():.1f} "
            f"steps; acceptance {self.acceptance:.2f}"
            + ("; CHAIN SHORTER THAN 50 τ" if self.short_chain else ""),
            "",
            "| parameter | LM value | LM std | posterior mean | posterior std | ratio |",
            "|---|---|---|---|---|---|",
        ]
        for k, n in enumerate(self.labels or self.names):
            ratio = self.std[k] / self.lm_std[k] if np.isfinite(self.lm_std[k]) else np.nan
            lines.append(
                f"| {n} | {self.lm_value[k]:.6g} | {self.lm_std[k]:.3g} | {self.mean[k]:.6g} "
                f"| {self.std[k]:.3g} | {ratio:.3f} |"
            )
        if self.fixed_directions:
            lines.append("")
            lines.append(f"{len(self.fixed_directions)} unidentifiable direction(s) held fixed.")
        return "\n".join(lines)


def _whitening(cal: Calibration):
    """(P_free, r) L with L Lᵀ = the LM covariance (a pseudo-inverse of rank r = cal.rank):
    eigenvectors of its correlation form, so mm, rad and mm/rev do not mix in the cut."""
    cov = np.asarray(cal.covariance, float)
    d = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    on = d > 0
    dd = np.where(on, d, 1.0)
    C = cov / np.outer(dd, dd)
    lam, E = np.linalg.eigh(C)
    r = int(cal.rank)
    lam, E = lam[::-1][:r], E[:, ::-1][:, :r]
    if r == 0 or lam[-1] <= 0:
        raise ValueError("the calibration has no identifiable direction to sample")
    return dd[:, None] * E * np.sqrt(lam), r


@jit
def _log_prob_batch(z, problem, layout, template, center, L, inv_prior_var, tolerance_w):
    """Log-posterior (W,) of W walkers z (W, r): one vmapped residual evaluation.
    `tolerance_w` (P,): 1 / σ of the set-up's prior from the tolerances (`Setup.prior`;
    zeros: none)."""
    _, unravel = ravel_pytree(template)

    def one(zi):
        flat = center + L @ zi
        r = residual(unravel(flat), (problem, layout))
        lp = -0.5 * jnp.sum(r**2) - 0.5 * inv_prior_var * jnp.sum(zi**2)
        lp = lp - 0.5 * jnp.sum((tolerance_w * flat) ** 2)
        return jnp.where(jnp.isfinite(lp), lp, -jnp.inf)

    return jax.vmap(one)(z)


def _free_index(st: Setup, cal: Calibration) -> np.ndarray:
    pos = {n: k for k, n in enumerate(st.names)}
    missing = [n for n in cal.names if n not in pos]
    if missing:
        raise ValueError(
            f"the calibration's parameters {missing[:3]} are not in the setup: pass the Setup "
            "the calibration was fitted from"
        )
    return np.array([pos[n] for n in cal.names], int)


@one_blas_thread
def posterior(
    st: Setup,
    cal: Calibration,
    *,
    n_walkers: int | None = None,
    n_steps: int = 2000,
    burn: int | None = None,
    thin: int | None = None,
    seed: int = 0,
    progress: bool = True,
    prior_scale: float | None = 100.0,
    rows=None,
) -> PosteriorResult:
    """Sample the posterior of the parameters `cal` estimated from `st` (`cal = fit(st, ...)`).

    - `n_walkers`: even, >= 2 r + 2 (default: max(16, 2 r + 2)), r the number of
      identifiable directions (the sampled dimensions);
    - `n_steps`: steps per walker; `burn`, `thin`: steps dropped at the start and kept every
      `thin` (default: burn = max(n_steps // 5, 3 τ_max) capped at n_steps // 2, thin =
      max(1, τ_max // 2));
    - `prior_scale`: see the module docstring (None = flat); `rows`: the data rows the fit
      used (as in `fit`; default all);
    - moves: 0.8 `emcee.moves.DEMove` + 0.2 `SnookerMove` (a corrected DESnookerMove, see
      its docstring); walkers start at N(0, I) in the whitened coordinates (the Laplace
      approximation), so burn-in is short.

    Emits a `UserWarning` (and sets `short_chain`) when the chain is shorter than 50 times
    the integrated autocorrelation time (emcee's `AutocorrError`), then uses the estimate.
    """
    if cal.covariance is None:
        raise ValueError("the calibration has no covariance (was it made by `fit`?)")
    if n_steps < 10:
        raise ValueError(f"n_steps must be at least 10, got {n_steps}")
    if prior_scale is not None and not prior_scale > 0:
        raise ValueError(f"prior_scale must be positive or None, got {prior_scale}")
    if burn is not None and not 0 <= burn < n_steps:
        raise ValueError(f"burn must be in [0, n_steps = {n_steps}), got {burn}")
    if thin is not None and thin < 1:
        raise ValueError(f"thin must be >= 1, got {thin}")
    index = _free_index(st, cal)
    Lf, r = _whitening(cal)
    flat_lm, _ = ravel_pytree(cal.theta)
    L = np.zeros((flat_lm.shape[0], r))
    L[index] = Lf
    if n_walkers is None:
        n_walkers = max(16, 2 * r + 2)
        n_walkers += n_walkers % 2
    if n_walkers % 2 or n_walkers < 2 * r + 2:
        raise ValueError(f"n_walkers must be even and >= 2 r + 2 = {2 * r + 2}, got {n_walkers}")

    problem = st.problem
    if cal.weight is not None:  # the fit's weights: the σ it used (stated or estimated)
        problem = eqx.tree_at(lambda p: p.weight, problem, jnp.asarray(cal.weight))
    if rows is not None:
        use = np.zeros(len(st.mask), bool)
        use[np.asarray(rows)] = True
        problem = eqx.tree_at(
            lambda p: p.weight, problem, problem.weight * jnp.asarray(use, float)[:, None]
        )
    args = (
        problem,
        st.layout,
        cal.theta,
        flat_lm,
        jnp.asarray(L),
        jnp.asarray(0.0 if prior_scale is None else 1.0 / prior_scale**2),
        jnp.asarray(np.zeros(flat_lm.shape[0]) if st.prior is None else st.prior),
    )

    def log_prob(z):
        return np.asarray(_log_prob_batch(jnp.asarray(z), *args))

    import emcee  # here, not at import (`moves`)

    from .moves import SnookerMove

    rng = np.random.default_rng(seed)
    p0 = rng.normal(size=(n_walkers, r))
    sampler = emcee.EnsembleSampler(
        n_walkers,
        r,
        log_prob,
        vectorize=True,
        moves=[(emcee.moves.DEMove(), 0.8), (SnookerMove(), 0.2)],
    )
    # initial log-probabilities in two halves: every call then has the moves' batch shape W/2
    lp0 = np.concatenate([log_prob(p0[: n_walkers // 2]), log_prob(p0[n_walkers // 2 :])])
    state = emcee.State(p0, log_prob=lp0, random_state=np.random.RandomState(seed).get_state())
    sampler.run_mcmc(state, n_steps, progress=progress)

    short = False
    try:
        tau = np.asarray(sampler.get_autocorr_time())
    except emcee.autocorr.AutocorrError as err:
        tau = np.asarray(err.tau)
        short = True
    # a chain of a few steps can leave τ undefined (NaN): take the whole run as one τ then
    tau_max = float(np.nanmax(tau)) if np.isfinite(tau).any() else float(n_steps)
    if short:
        warnings.warn(
            f"posterior: the chain ({n_steps} steps) is shorter than 50 autocorrelation times "
            f"(max τ ≈ {tau_max:.1f} steps): the estimates are rough; run >= "
            f"{int(np.ceil(50 * tau_max))} steps",
            UserWarning,
            stacklevel=2,
        )
    if burn is None:
        burn = min(max(n_steps // 5, int(np.ceil(3 * tau_max))), n_steps // 2)
    if thin is None:
        thin = max(1, int(tau_max // 2))
    z = sampler.get_chain(discard=burn, thin=thin, flat=True)
    lp = sampler.get_log_prob(discard=burn, thin=thin, flat=True)
    samples = np.asarray(flat_lm)[index] + z @ Lf.T
    ident = np.isfinite(cal.std)
    mean = samples.mean(0)
    std = np.where(ident, samples.std(0, ddof=1), np.inf)
    return PosteriorResult(
        names=list(cal.names),
        labels=list(cal.labels or cal.names),
        samples=samples,
        log_prob=lp,
        mean=mean,
        std=std,
        lm_value=np.asarray(cal.value),
        lm_std=np.asarray(cal.std),
        identifiable=ident,
        fixed_directions=list(cal.unidentifiable),
        tau=tau,
        acceptance=float(np.mean(sampler.acceptance_fraction)),
        short_chain=short,
        n_walkers=int(n_walkers),
        n_steps=int(n_steps),
        burn=int(burn),
        thin=int(thin),
        rank=int(r),
        theta_lm=cal.theta,
        index=index,
        whitening=L,
    )


# --- plots ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class PredictiveBands:
    """Posterior-predictive pose error over commanded poses.

    - `poses` (Q, 6): commanded poses (mm, rad); `percentiles` (B,) in %;
    - `bands` (B, Q, 6): percentiles over the posterior samples of the pose error
      (`pose_error` of the pose reached against the pose commanded: translation mm,
      rotation vector rad);
    - `lm` (Q, 6): the pose error predicted by the LM fit; `samples` (S, Q, 6): the errors of
      the drawn sample tables; `failed`: number of (sample, pose) solves that did not
      converge (their errors are NaN and left out of the percentiles).
    """

    poses: np.ndarray
    percentiles: np.ndarray
    bands: np.ndarray
    lm: np.ndarray
    samples: np.ndarray
    failed: int


@jit
def _pose_errors(thetas, problem, layout, s, poses, options):
    """Pose errors (S, Q, 6) (`pose_error`: translation mm, rotation vector rad) and
    success flags (S, Q) of S parameter pytrees (leading axis) at the actuator extensions
    s (Q, 6) the controller gives for `poses` (Q, 6)."""

    def per_sample(theta):
        table, effects, *_ = build_model(problem, layout, theta)

        def per_pose(si, qi):
            q, result, _, _ = forward_one(table, effects, si, qi, options)
            return pose_error(q, qi), result == RESULTS.successful

        return jax.vmap(per_pose)(s, poses)

    return jax.vmap(per_sample)(thetas)


def predictive_bands(
    st: Setup,
    result: PosteriorResult,
    poses,
    *,
    n_samples: int = 200,
    percentiles=(2.5, 50.0, 97.5),
    compensated: bool = True,
    compensate: bool | None = None,
    seed: int = 0,
    options: ForwardOptions = ForwardOptions(),
) -> PredictiveBands:
    """Posterior-predictive pose error at commanded `poses` (Q, 6), mm / rad.

    The controller believes the nominal table of `st` and commands its inverse kinematics
    (`actuator_command(nominal, poses, compensated)`); each of `n_samples` posterior draws
    (with the fitted effects, home context: direction +1, 20 °C, no payload) settles at the
    exact forward-kinematics pose for those commands; its error is the `pose_error` of that
    pose against the commanded one. Returns percentile bands per pose and column, and the
    LM prediction. Joint sets fitted modulo rigid motions (the gauge) are compared in that gauge.
    """
    poses = np.asarray(poses, float)
    if poses.ndim != 2 or poses.shape[1] != 6 or not np.isfinite(poses).all():
        raise ValueError(f"poses must be a finite (Q, 6) array, got shape {poses.shape}")
    pct = np.asarray(percentiles, float)
    if np.any((pct < 0) | (pct > 100)):
        raise ValueError(f"percentiles must lie in [0, 100], got {pct}")
    nominal = st.problem.nominal
    compensated = renamed_argument(
        compensated, compensate, "compensate", "compensated", "predictive_bands"
    )
    cmd = np.asarray(actuator_command(nominal, poses, compensated))
    s = jnp.asarray(cmd - np.asarray(nominal.zero_lengths))
    flat_lm, unravel = ravel_pytree(result.theta_lm)
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(result.samples), min(n_samples, len(result.samples)), replace=False)
    flats = np.tile(np.asarray(flat_lm), (len(pick) + 1, 1))
    flats[1:, result.index] = result.samples[pick]
    thetas = jax.vmap(unravel)(jnp.asarray(flats))
    err, ok = _pose_errors(thetas, st.problem, st.layout, s, jnp.asarray(poses), options)
    err, ok = np.asarray(err), np.asarray(ok)
    if not ok[0].all():
        bad = np.flatnonzero(~ok[0]) + 1
        raise KinematicsError(
            f"forward kinematics of the fitted table (the fit's optimum) failed at {len(bad)} "
            f"of the {len(poses)} commanded pose(s): {bad.tolist()[:10]}"
            + (" ..." if len(bad) > 10 else "")
            + " (1-based); are they inside the workspace?"
        )
    samp = np.where(ok[1:, :, None], err[1:], np.nan)
    bands = np.nanpercentile(samp, pct, axis=0)
    return PredictiveBands(poses, pct, bands, err[0], samp, int((~ok[1:]).sum()))
