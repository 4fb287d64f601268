"""A Gaussian-process residual model: how much of what a fitted model leaves could *any*
smooth leg-length error explain on held-out rows? The ceiling a named finding is measured
against, and a way to see structure without naming it.

Model. Each reading's residual is the fitted model's linear part plus the reading's view of
an unknown extra length g on every leg, plus noise:

    e = J β + B g + ε,   ε ~ N(0, s² I)          (whitened: σ-normalised readings)

J the fit's weighted Jacobian (free columns; β flat: the geometry, frames and effects are
refitted with the GP, never fought by it), B the readings' response to leg lengths (the
`zero_lengths` columns of the full Jacobian, row by row: an extra length on leg i at stop n
moves stop n's readings by B_n[:, i]), and g a Gaussian process over (stop n, leg i),

    cov(g_ni, g_mj) = K_shared((n, i), (m, j)) + δ_ij σ_i² K_leg((n, i), (m, i)),

two additive kernels (sums of one-dimensional squared-exponential components, each with its
weight; every feature has one length scale). The shared part is one function, the same for
every leg, of the leg's own features: its extension s_i, its direction of travel d_i, and
the stop's temperature T, time t (0..1 over the run), session index and payload; components:
each feature alone, and s_i times each other one (a scale that depends on it). The per-leg
part is a function for each leg (amplitude σ_i) of the same features and of every leg's
extension s_1..s_6 (crosstalk): each alone, and s_i times each of d_i, T, t, session, payload.
An additive kernel is what about a hundred stops can support: a full ARD product over eleven
features fitted the noise and gained nothing on held-out rows. Features are standardised
(extensions by their common spread, so legs compare); a component of a feature that does not
vary in the data has weight zero.

Hyper-parameters (weights, length scales, σ_i, s) maximise the restricted likelihood (REML:
the likelihood of the residuals with J's coefficients integrated out, so the GP never takes
what the geometry can do), with weak log-normal priors (length scales: median 1 standardised
unit, log-sd 1; weights: median 1, log-sd 2) that keep flat directions finite, and a floor on
the white noise relative to the GP's prior variance (`NOISE_FLOOR`) that keeps the
covariance well conditioned, by BFGS
(optimistix; it also stops where the gradient is flat, `_BFGS`: the per-leg amplitudes σ_i
have no prior, and those the data do not support fall towards zero). They are fitted once on
all rows; held-out predictions then refit β and condition g on the other folds' rows only
(the GP predictor with explicit basis functions: generalised least squares for β, kriging of
what is left). Fitting the hyper-parameters on every row makes the held-out gain a slight
overestimate: a ceiling, as intended.

A run longer than `MAX_ROWS` stops is modelled on that many stops spread evenly over it (the
cost grows as the cube of the stops and the covariance as their square; a few hundred stops
say what the residuals depend on as well as thousands would).
"""

from dataclasses import dataclass
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.scipy.linalg import solve_triangular

from .._calibration.fit import Calibration, Setup
from .._calibration.heldout import make_folds
from .._calibration.noise import fit_basis
from .._jit import device_array, jit
from .._threads import one_blas_thread

ROW = ("temperature", "time", "session", "payload")  # features of the stop, not the leg
SHARED = (
    ("own extension s_i", "direction d_i")
    + ROW
    + tuple(f"s_i × {f}" for f in ("direction d_i",) + ROW)
)
PER_LEG = (
    tuple(f"extension s_{j}" for j in range(1, 7))
    + ("direction d_i",)
    + ROW
    + tuple(f"s_i × {f}" for f in ("direction d_i",) + ROW)
)
LOG_ELL_SD = 1.0  # prior log-sd of a length scale (median 1 standardised unit)
LOG_W_SD = 2.0  # prior log-sd of a component weight (median 1)
MAX_ROWS = 200  # stops the residual model is fitted on (spread over a longer run)
NOISE_FLOOR = 1e-8
"""Least white-noise variance of a reading, as a fraction of the GP part's mean prior
variance of a reading (`_white`): the GP explains its readings to at most 1 part in 10⁴ of
its own prior amplitude. Without it, residuals that an additive squared-exponential kernel can
only reach in its polynomial limit (amplitudes and length scales growing together, the
constant and linear parts hidden in the fit's basis) drove the per-leg amplitudes to variances
of ~10¹² σ² and the covariance to condition numbers past 10¹⁴ (numerically indefinite): the
likelihood was then rounding noise, and where the fit ended, its gain and its hints changed
with perturbations of the residuals of 1e-9 (held-out gain 55–76 %, log evidence −22 to 336
on one file). With it those fits end at one optimum whatever the rounding (`tests/test_gp.py`:
2e-6 apart in the log evidence). Where the fitted s² stays above the floor the model is the
one without it (s takes what the floor adds): the 108 planted and noise-only runs of
`studies/discovery_baselines.py` keep every GP gain to 1e-7 and every hint."""


@dataclass(frozen=True)
class ResidualGP:
    """Outcome of `residual_gp`.

    - `heldout_rms_model`, `heldout_rms_gp`: k-fold held-out RMS of the σ-normalised
      residuals (the fit's σ) of the fitted model, and of the model plus the GP;
      `gain` = 1 − gp / model (0: nothing smooth left; the ceiling of what a named term can
      gain on these folds);
    - `components`: {"shared: <component>" or "leg i: <component>": variance} the prior
      variance of each additive component of g (σ² of the readings per unit response),
      largest first: what the residuals depend on;
    - `noise`: the white noise of a reading, √(s² + the floor, `NOISE_FLOOR`) (1.0: the
      residuals' noise is the fit's σ); `log_evidence`: the restricted
      log likelihood at the optimum (priors included); `converged`, `steps` (BFGS steps,
      line-search trials included); `folds`, `grouped`;
    - `rows`: the stops the model was fitted and scored on (indices into the data; all of
      them up to `max_rows`, else that many spread evenly over the run), `rows_total`.
    """

    heldout_rms_model: float
    heldout_rms_gp: float
    gain: float
    components: dict
    noise: float
    log_evidence: float
    converged: bool
    steps: int
    folds: int
    grouped: bool
    rows: np.ndarray
    rows_total: int

    def scope(self) -> str:
        """ "" when every stop was used, else " (on M of N stops, spread over the run)"."""
        if len(self.rows) == self.rows_total:
            return ""
        return f" (on {len(self.rows)} of {self.rows_total} stops, spread over the run)"

    def hints(self, share: float = 0.1) -> list[str]:
        """The components whose variance is at least `share` of the largest, largest first."""
        top = max(self.components.values(), default=0.0)
        return [k for k, v in self.components.items() if top > 0 and v >= share * top]


def _features(st: Setup):
    """Standardised features: own extension s (N, 6), direction d (N, 6), row features
    R (N, 4) (temperature, time, session, payload), and which vary: (own s, d, R...) (6,)."""
    problem = st.problem
    ctx = problem.ctx
    s = np.asarray(problem.s, float)
    d = np.asarray(ctx.direction, float)
    R = np.stack([np.asarray(getattr(ctx, k), float) for k in ROW], axis=1)

    def z(x, axis=None):
        sd = np.std(x, axis=axis)
        return (x - np.mean(x, axis=axis)) / np.where(sd > 1e-9, sd, 1.0), sd > 1e-9

    s_z, s_v = z(s)
    R_z, R_v = z(R, axis=0)
    vary = np.concatenate([[s_v, np.std(d) > 1e-9], R_v])
    return s_z, d, R_z, vary


def _se(x, y, ell):
    """Squared-exponential kernel of 1-D features: x (..., M), y (..., M') -> (..., M, M')."""
    r = (x[..., :, None] - y[..., None, :]) / ell
    return jnp.exp(-0.5 * r * r)


def _latent_cov(h, s, d, R, vary):
    """(N, 6, N, 6) prior covariance of the leg-length errors g for log hyper-parameters h.

    s, d (N, 6): own extension and direction; R (N, 4): row features; vary (6,) 0/1."""
    n = s.shape[0]
    ell_o, ell_a = jnp.exp(h["ell_own"]), jnp.exp(h["ell_all"])
    v_R = vary[2:]
    w_sh = jnp.exp(2.0 * h["w_shared"]) * jnp.concatenate([vary[:2], v_R, vary[1:2], v_R])
    w_lg = jnp.exp(2.0 * h["w_legs"]) * jnp.concatenate(
        [jnp.full(6, vary[0]), vary[1:2], v_R, vary[1:2], v_R]
    )
    # row kernels (4, N, N) with the own length scales (shared part) and the per-leg ones
    kR_o = _se(R.T, R.T, ell_o[2:, None, None])
    kR_a = _se(R.T, R.T, ell_a[7:, None, None])
    # shared part over (n, i) pairs
    sf, df = s.reshape(-1), d.reshape(-1)
    ks = _se(sf, sf, ell_o[0])
    kd = _se(df, df, ell_o[1])
    row_alone = jnp.einsum("f,fnm->nm", w_sh[2:6], kR_o)
    row_times_s = jnp.einsum("f,fnm->nm", w_sh[7:11], kR_o)

    def rows(k):  # (N, N) -> (N·6, N·6): the same for every pair of legs
        return jnp.broadcast_to(k[:, None, :, None], (n, 6, n, 6)).reshape(n * 6, n * 6)

    K = (
        w_sh[0] * ks + w_sh[1] * kd + rows(row_alone) + ks * (w_sh[6] * kd + rows(row_times_s))
    ).reshape(n, 6, n, 6)
    # per-leg part: (6, N, N), leg i with leg i only
    kS = _se(s.T, s.T, ell_a[:6, None, None])  # the legs' extensions, row features
    kS_all = jnp.einsum("j,jnm->nm", w_lg[:6], kS)
    kd_leg = _se(d.T, d.T, ell_a[6])
    ks_leg = _se(s.T, s.T, ell_o[0])
    K_leg = (
        kS_all[None]
        + w_lg[6] * kd_leg
        + jnp.einsum("f,fnm->nm", w_lg[7:11], kR_a)[None]
        + ks_leg * (w_lg[11] * kd_leg + jnp.einsum("f,fnm->nm", w_lg[12:16], kR_a)[None])
    )
    K_leg = K_leg * jnp.exp(2.0 * h["legs"])[:, None, None]
    return K + jnp.einsum("inm,ij->nimj", K_leg, jnp.eye(6))


def _reading_cov(h, A, s, d, R, vary, obs):
    """(n_obs, n_obs) covariance B K Bᵀ of the readings' GP part: B is block diagonal (one
    (6 readings × 6 legs) block `A` per stop), so it is applied block by block."""
    n = A.shape[0]
    K = _latent_cov(h, s, d, R, vary)
    T = jnp.einsum("nai,nimj->namj", A, K)
    C = jnp.einsum("namj,mbj->namb", T, A).reshape(n * 6, n * 6)
    return C[obs][:, obs]


_reading_cov_jit = jit(_reading_cov)


def _reml_parts(C, y, U):
    L = jnp.linalg.cholesky(C)
    a = solve_triangular(L, y, lower=True)
    V = solve_triangular(L, U, lower=True)
    Lg = jnp.linalg.cholesky(V.T @ V)
    b = solve_triangular(Lg, V.T @ a, lower=True)
    nll = 0.5 * (a @ a - b @ b) + jnp.sum(jnp.log(jnp.diag(L))) + jnp.sum(jnp.log(jnp.diag(Lg)))
    return nll, (L, V, Lg, a, b)


@jax.custom_vjp
def _reml(C, y, U):
    """REML negative log likelihood of residuals y (n,) with covariance C (n, n) and basis
    U (n, p): ½ yᵀPy + ½ log|C| + ½ log|UᵀC⁻¹U|, P = C⁻¹ − C⁻¹U(UᵀC⁻¹U)⁻¹UᵀC⁻¹.

    Its derivatives are the closed forms (`_reml_bwd`): ∂/∂C = ½(P − P y yᵀ P), ∂/∂y = P y,
    ∂/∂U = C⁻¹U(UᵀC⁻¹U)⁻¹ − P y βᵀ (β the generalised least-squares coefficients). Reverse
    mode through the Cholesky factor instead took two triangular solves and a product of
    n × n matrices (~60 ms at n = 900, most of a hyper-parameter step); P takes a triangular
    inverse and a product of triangles, in blocks (`_lower_inverse`, `_lower_gram`): a GP
    fit of 150 stops 11.2–11.5 → 6.7–6.8 s, the same steps and optimum."""
    return _reml_parts(C, y, U)[0]


def _reml_bwd(parts, g):
    L, V, Lg, a, b = parts
    Li = _lower_inverse(L)
    Q = solve_triangular(Lg, V.T, lower=True)  # Lg⁻¹ Vᵀ (p, n)
    Z = Li.T @ Q.T  # C⁻¹ U Lg⁻ᵀ: C⁻¹U(UᵀC⁻¹U)⁻¹Uᵀ C⁻¹ = Z Zᵀ
    Py = Li.T @ (a - Q.T @ b)
    beta = solve_triangular(Lg, b, lower=True, trans="T")
    dC = 0.5 * g * (_lower_gram(Li) - Z @ Z.T - jnp.outer(Py, Py))
    dU = g * (solve_triangular(Lg, Z.T, lower=True, trans="T").T - jnp.outer(Py, beta))
    return dC, g * Py, dU


_reml.defvjp(_reml_parts, _reml_bwd)  # forward: the value and what the closed forms read


def _lower_inverse(L):
    """L⁻¹ of a lower-triangular L (n, n), by 2 × 2 blocks down to 128 rows: a triangular
    solve of the identity does n³ multiplications, the blocks about half of that."""
    n = L.shape[0]
    if n < 256:
        return solve_triangular(L, jnp.eye(n), lower=True)
    k = n // 2
    Ai, Di = _lower_inverse(L[:k, :k]), _lower_inverse(L[k:, k:])
    return jnp.block([[Ai, jnp.zeros((k, n - k))], [-Di @ (L[k:, :k] @ Ai), Di]])


def _lower_gram(M):
    """MᵀM of a lower-triangular M (n, n), by 2 × 2 blocks down to 128 rows (about half the
    multiplications of the full product)."""
    n = M.shape[0]
    if n < 256:
        return M.T @ M
    k = n // 2
    B, D = M[k:, :k], M[k:, k:]
    top = _lower_gram(M[:k, :k]) + B.T @ B
    side = B.T @ D
    return jnp.block([[top, side], [side.T, _lower_gram(D)]])


def _white(s2, G):
    """White-noise variance of a reading: the fitted s² plus the floor (`NOISE_FLOOR` times
    the mean diagonal of the GP part's covariance G of the readings). numpy or jax arrays."""
    return s2 + NOISE_FLOOR * G.trace() / G.shape[0]


def _neg_log_posterior(h, args):
    """REML negative log likelihood (+ the weak priors) of residuals y with basis U."""
    y, U, A, s, d, R, vary, obs = args
    G = _reading_cov(h, A, s, d, R, vary, obs)
    C = G + _white(jnp.exp(2.0 * h["noise"]), G) * jnp.eye(len(y))
    nll = _reml(C, y, U)
    prior = 0.5 * (jnp.sum(h["ell_own"] ** 2) + jnp.sum(h["ell_all"] ** 2)) / LOG_ELL_SD**2
    prior += 0.5 * (jnp.sum(h["w_shared"] ** 2) + jnp.sum(h["w_legs"] ** 2)) / LOG_W_SD**2
    return nll + prior


class _BFGS(optx.BFGS):
    """optimistix's BFGS that also stops where every gradient component is under `GTOL`.

    The amplitudes of components the residuals do not support (a leg's σ_i with nothing of
    its own) have no prior and fall towards zero without bound: the objective is flat there
    and its gradient vanishes, but their logarithm keeps moving, so the Cauchy test on the
    iterates (`rtol`) never holds. Stopping at a small gradient ends at the same optimum
    (the objective within ~1e-6 of the longer run) in about half the steps."""

    GTOL: ClassVar[float] = 1e-4  # on the negative log posterior, per log hyper-parameter

    def step(self, fn, y, args, options, state, tags):
        y, state, aux = super().step(fn, y, args, options, state, tags)
        worst = jnp.max(
            jnp.stack([jnp.max(jnp.abs(g)) for g in jax.tree.leaves(state.f_info.grad)])
        )
        flat = (worst < self.GTOL) & (state.num_accepted_steps > 1)
        return y, eqx.tree_at(lambda s: s.terminate, state, state.terminate | flat), aux


@jit
def _fit_hyper(h0, args, max_steps):
    solver = _BFGS(rtol=1e-6, atol=1e-6)
    sol = optx.minimise(_neg_log_posterior, solver, h0, args, max_steps=max_steps, throw=False)
    ok = sol.result == optx.RESULTS.successful
    return sol.value, _neg_log_posterior(sol.value, args), ok, sol.stats["num_steps"]


@jit
def _conditional(Call, noise, t, f, U, y):
    """GP-with-basis prediction of the readings `f` from the readings `t` (indices into the
    measured readings), given the GP part's covariance `Call` of all measured readings and
    the noise s: generalised least squares for the basis, kriging of the rest."""
    U_T, U_F, y_T = U[t], U[f], y[t]
    C = Call[t][:, t] + noise**2 * jnp.eye(len(t))
    L = jnp.linalg.cholesky(C)
    Lu = solve_triangular(L, U_T, lower=True)
    Ly = solve_triangular(L, y_T, lower=True)
    beta = jnp.linalg.lstsq(Lu, Ly, rcond=1e-10)[0]
    w = jax.scipy.linalg.cho_solve((L, True), y_T - U_T @ beta)
    return U_F @ beta + Call[f][:, t] @ w


@one_blas_thread
def residual_gp(
    cal: Calibration,
    st: Setup,
    *,
    folds: int = 5,
    grouped: bool = True,
    seed: int = 0,
    max_steps: int = 500,
    tol: float = 1e-6,
    max_rows: int = MAX_ROWS,
) -> ResidualGP:
    """Fit the GP residual model (module docstring) to the residuals of fit `cal` of set-up
    `st` (`diagnose`'s `Diagnosis.base` / `.final` and `.setup`, or `setup` + `fit`), and
    score it on `folds` held-out folds (`grouped`: contiguous stretches of the run, as the
    discovery dictionary's gains are scored; else rows dealt at random).

    Its cost grows as the cube of the stops (the fit of the hyper-parameters on two cores:
    100 stops ~1–2 s, 200 ~8 s, 400 about a minute by the cube; the first call of a size
    compiles for ~4 s more; its covariance holds (6 N)² numbers): a longer run is
    modelled on `max_rows` stops spread evenly over it (every k-th, so each session, the
    temperature and time ranges keep their share), which is what the hints need; `rows`
    says which."""
    if cal.jacobian_full is None or cal.residual is None:
        raise ValueError("residual_gp needs a fit with its full Jacobian (diagnose's, or fit())")
    mask_all = np.asarray(st.mask, bool)
    n_all = mask_all.shape[0]
    if n_all < min_rows(folds):
        raise ValueError(
            f"residual_gp needs at least {min_rows(folds)} rows for {folds} folds; got {n_all}"
        )
    if max_rows < min_rows(folds):
        raise ValueError(f"max_rows must be at least {min_rows(folds)} for {folds} folds")
    keep = spread_rows(n_all, max_rows)
    mask = mask_all[keep]
    n = len(keep)
    obs = np.flatnonzero(mask.reshape(-1))
    # the kept stops' measured readings, as indices into the fit's N·6 readings
    reading = (keep[:, None] * 6 + np.arange(6)).reshape(-1)[mask.reshape(-1)]
    y = np.asarray(cal.residual, float).reshape(-1)[reading]
    U = fit_basis(np.asarray(cal.jacobian, float)[reading], tol)
    zl = [st.names.index(f"zero_lengths[{i}]") for i in range(1, 7)]
    A = np.asarray(cal.jacobian_full, float)[:, zl].reshape(n_all, 6, 6)[
        keep
    ]  # (row, reading, leg)
    A = A / float(np.sqrt(np.sum(A**2) / max(len(obs), 1)))  # g in σ per unit response
    s, d, R, vary = _features(st)  # standardised over the whole run
    s, d, R = s[keep], d[keep], R[keep]

    # REML: the likelihood of the residuals with the fit's coefficients integrated out
    s0 = float(np.sqrt(np.sum(y**2) / max(len(y) - U.shape[1], 1)))
    h0 = {  # made in numpy (`device_array`): eager jnp compiles a program per shape
        "w_shared": np.full(len(SHARED), np.log(0.1 * s0)),
        "w_legs": np.full(len(PER_LEG), np.log(0.1)),
        "legs": np.full(6, np.log(s0)),
        "ell_own": np.zeros(6),
        "ell_all": np.zeros(11),
        "noise": np.log(s0),
    }
    h0 = {k: device_array(v) for k, v in h0.items()}
    args = tuple(device_array(a) for a in (y, U, A, s, d, R, vary.astype(float), obs))
    h, nlp, ok, steps = _fit_hyper(h0, args, max_steps)
    h = jax.tree.map(np.asarray, h)

    rows = make_folds(n, folds, seed, grouped=grouped, strata=np.asarray(st.problem.session)[keep])
    pos = np.full(n * 6, -1)
    pos[obs] = np.arange(len(obs))
    sq_m = sq_g = 0.0
    count = 0
    Call = _reading_cov_jit(h, *args[2:])  # the GP part's covariance, shared by every fold
    # the white noise with its floor; an array: as a Python float it would be built into the
    # program
    noise = np.sqrt(_white(np.exp(2.0 * h["noise"]), np.asarray(Call)))
    for r in rows:
        f = pos[(r[:, None] * 6 + np.arange(6)).reshape(-1)]
        f = f[f >= 0]
        t = np.setdiff1d(np.arange(len(obs)), f)
        beta = np.linalg.lstsq(U[t], y[t], rcond=1e-10)[0]
        sq_m += float(np.sum((y[f] - U[f] @ beta) ** 2))
        pred = _conditional(Call, noise, t, f, U, y)
        sq_g += float(np.sum((y[f] - np.asarray(pred)) ** 2))
        count += len(f)
    rms_m, rms_g = np.sqrt(sq_m / count), np.sqrt(sq_g / count)
    v_sh = np.concatenate([vary[:2], vary[2:], vary[1:2], vary[2:]])
    v_lg = np.concatenate([np.full(6, vary[0]), vary[1:2], vary[2:], vary[1:2], vary[2:]])
    comp = {
        f"shared: {k}": float(np.exp(2 * w)) for k, w, v in zip(SHARED, h["w_shared"], v_sh) if v
    }
    for i, sl in enumerate(np.exp(2 * h["legs"])):
        for k, w, v in zip(PER_LEG, h["w_legs"], v_lg):
            if v:
                comp[f"leg {i + 1}: {k}"] = float(sl * np.exp(2 * w))
    components = dict(sorted(comp.items(), key=lambda kv: -kv[1]))
    return ResidualGP(
        heldout_rms_model=float(rms_m),
        heldout_rms_gp=float(rms_g),
        gain=float(1.0 - rms_g / rms_m),
        components=components,
        noise=float(noise),
        log_evidence=float(-nlp),
        converged=bool(ok),
        steps=int(steps),
        folds=folds,
        grouped=grouped,
        rows=keep,
        rows_total=n_all,
    )


def min_rows(folds: int) -> int:
    """The fewest stops `residual_gp` models with `folds` held-out folds: two a fold."""
    return 2 * folds


def spread_rows(n: int, m: int) -> np.ndarray:
    """All of range(n) when n ≤ m, else m indices spread evenly from the first to the last."""
    if n <= m:
        return np.arange(n)
    return np.unique(np.round(np.linspace(0, n - 1, m)).astype(int))
