"""Pose selection for calibration: choose K measurement poses from a candidate set so that
the fitted parameters are as well determined as possible (optimal experimental design).

Model. The identification Jacobian of a candidate pose is the Jacobian of the fit's own
weighted residual (`_calibrate.residual`: exact forward kinematics, the instrument's view in
its frame, residual / σ) with respect to the fitted parameters (table leaves, effect fields,
and the instrument frame and target as nuisance parameters, joint sets modulo rigid motions
as in `calibrate`), at the nominal table: rows (m, P) per pose, m = the columns the
instrument measures. A design S (a set of poses) has the Fisher information

    F_S = Σ_{i ∈ S} J_iᵀ J_i          (P, P), parameter covariance ≈ F_S⁻¹

Criteria are computed in column-scaled coordinates (each parameter divided by the RMS over
the candidates of its Jacobian column, so mm, rad and mm/rev weigh alike; D-optimality is
invariant to this scaling) and restricted to the r directions the whole candidate set can
identify (singular values above `tol` × the largest); a direction no candidate can see is
reported, not optimised:

- "D": maximise log det F_S (the volume of the confidence ellipsoid shrinks);
- "A": minimise trace F_S⁻¹ (the mean scaled parameter variance).

Search: greedy additions (each step scores every candidate at once with the matrix
determinant lemma, log det(F + GᵀG) = log det F + log det(I_m + G F⁻¹ Gᵀ), on a small ridge
ε·I that makes the first steps well posed), then Fedorov exchange passes (swap a chosen pose
for the best candidate while the criterion improves). Observability indices of the chosen
design: O1 = (σ_1 ⋯ σ_r)^(1/r) / √K and the smallest singular value σ_r / √K of the scaled
Jacobian (Sun & Hollerbach's O1 and a minimum-singular-value index).
"""

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from .. import _params as params
from .._batch import run_batch
from .._forward import platform_radius
from .._jit import device_array, jit
from .._table import Table
from .._threads import one_blas_thread
from .fit import Layout, jacobian_in_chunks, make_problem, setup, zero_steps
from .instruments import Instrument, observe, readings
from .measurements import Measurements
from .simulate import plan_random

__all__ = [
    "DesignQuality",
    "PoseJacobians",
    "PoseSelection",
    "compare_with_random",
    "evaluate_design",
    "align_pose_errors",
    "pose_jacobians",
    "pose_sensitivities",
    "predicted_pose_error",
    "rigid_projector",
    "select",
    "select_poses",
]

DEFAULT_FREE = params.GEOMETRY
CRITERIA = ("D", "A")


@dataclass(frozen=True)
class PoseJacobians:
    """Identification Jacobians of M candidate poses.

    - `poses` (M, 6): candidates, mm / rad; `columns`: the m measured pose columns;
    - `jac` (M, m, P): d(weighted residual)/dθ per pose (1/σ times the reading's derivative:
      mm/σ per mm of a length parameter, etc.); Fisher information of a design = Σ jacᵀ jac;
    - `names` (P,): the parameters, as `Calibration.names`; `nuisance` (P,) bool: instrument
      frame / target components (estimated, but not what the calibration is for);
    - `layout`, `bases`, `effects`, `nominal`, `compensated`: the fit's parameterisation.
    """

    poses: np.ndarray
    columns: tuple
    jac: np.ndarray
    names: list
    nuisance: np.ndarray
    layout: Layout
    bases: dict
    effects: dict
    nominal: Table
    compensated: bool

    def subset(self, index) -> "PoseJacobians":
        """The same Jacobians for the candidates `index` only."""
        index = np.asarray(index)
        return PoseJacobians(
            self.poses[index],
            self.columns,
            self.jac[index],
            self.names,
            self.nuisance,
            self.layout,
            self.bases,
            self.effects,
            self.nominal,
            self.compensated,
        )


def _check_poses(poses, name: str) -> np.ndarray:
    poses = np.asarray(poses, dtype=float)
    if poses.ndim != 2 or poses.shape[1] != 6:
        raise ValueError(f"{name} must have shape (M, 6), got {poses.shape}")
    if not np.isfinite(poses).all():
        bad = int(np.flatnonzero(~np.isfinite(poses).all(1))[0])
        raise ValueError(f"{name}: row {bad + 1} is not finite")
    return poses


def pose_jacobians(
    nominal: Table,
    candidates,
    instrument: Instrument,
    free=DEFAULT_FREE,
    *,
    effects=None,
    compensated: bool = True,
    target=None,
) -> PoseJacobians:
    """Identification Jacobians (M, m, P) of the candidate poses (M, 6), mm / rad.

    Built exactly as a calibration of `free` (+ the instrument frame and target the
    instrument can see) would be, from noise-free readings of the nominal table at the
    candidates (σ = the instrument's noise), and linearised at the nominal table, the
    identity instrument frame and the target offset `target` (6,) (default: zero; give the
    planned target, mm / rad, when the instrument tracks one off the platform origin).
    Candidates whose commands leave the stroke are refused (row named).
    """
    poses = _check_poses(candidates, "candidates")
    mask = instrument.mask
    tgt = np.zeros(6) if target is None else np.asarray(target, float)
    if tgt.shape != (6,):
        raise ValueError(f"target must have shape (6,), got {tgt.shape}")
    reading = np.asarray(readings(poses, np.zeros_like(poses), tgt))
    noise = np.asarray(instrument.noise, float)
    data = Measurements(
        poses,
        np.where(mask, reading, np.nan),
        None,
        np.where(mask, noise, np.nan) * np.ones((len(poses), 1)),
    )
    st = setup(nominal, data, free, effects=effects, compensated=compensated)
    theta = dict(st.theta0)
    if "frame" in theta:
        theta["frame"] = jnp.zeros_like(theta["frame"])
    if "target" in theta:
        theta["target"] = jnp.asarray(tgt[list(st.layout.target_dofs)])
    J = jacobian_in_chunks(st.problem, st.layout, theta)[0]
    J = J.reshape(len(poses), 6, -1)[:, mask, :]
    nuisance = np.array([n.startswith(("frame[", "target.")) for n in st.names])
    return PoseJacobians(
        poses,
        tuple(k for k in range(6) if mask[k]),
        J,
        list(st.names),
        nuisance,
        st.layout,
        dict(st.problem.bases),
        st.effects,
        nominal,
        compensated,
    )


# --- criteria -------------------------------------------------------------------------------


def _reduce(jac: np.ndarray, tol: float):
    """Column scale (P,), basis (P, r) of the identifiable directions, reduced rows
    G (M, m, r)."""
    M, m, P = jac.shape
    flat = jac.reshape(M * m, P)
    scale = np.linalg.norm(flat, axis=0) / np.sqrt(M)
    scale[scale == 0] = 1.0
    _, sv, Vt = np.linalg.svd(flat / scale, full_matrices=False)
    keep = sv > tol * sv[0]
    V = Vt[keep].T
    return scale, V, (jac / scale) @ V


def _objective(F, G, criterion: str, nuisance=None):
    """Criterion value (to maximise) of F + G_iᵀ G_i for every candidate i: G (M, m, r).
    "Ds" (`nuisance`: indices of the nuisance parameters): log det F − log det F_nn, the
    D-criterion of the other parameters with the nuisance ones estimated alongside."""
    if criterion == "Ds":
        nn = jnp.asarray(nuisance)
        return _objective(F, G, "D") - _objective(F[nn][:, nn], G[..., nn], "D")
    L = jnp.linalg.cholesky(F)
    # B_i = G_i L⁻ᵀ so that G_i F⁻¹ G_iᵀ = B_i B_iᵀ
    B = jax.vmap(lambda g: jax.scipy.linalg.solve_triangular(L, g.T, lower=True).T)(G)
    eye = jnp.eye(G.shape[1])
    A = eye + jnp.einsum("imr,inr->imn", B, B)
    if criterion == "D":
        base = 2.0 * jnp.sum(jnp.log(jnp.diag(L)))
        chol = jnp.linalg.cholesky(A)
        return base + 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol, axis1=1, axis2=2)), axis=1)
    # "A", by Woodbury: −tr((F + GᵀG)⁻¹) = −tr F⁻¹ + tr((I + G F⁻¹ Gᵀ)⁻¹ G F⁻² Gᵀ)
    Finv = jax.scipy.linalg.cho_solve((L, True), jnp.eye(F.shape[0]))
    C = jnp.einsum("imr,rs->ims", G, Finv)  # G F⁻¹
    CCt = jnp.einsum("imr,inr->imn", C, C)
    return -jnp.trace(Finv) + jnp.trace(jnp.linalg.solve(A, CCt), axis1=1, axis2=2)


def _value(F, criterion: str, nuisance=None):
    """Criterion value (to maximise) of one information matrix F (r, r)."""
    if criterion == "Ds":
        nn = jnp.asarray(nuisance)
        return _value(F, "D") - _value(F[nn][:, nn], "D")
    L = jnp.linalg.cholesky(F)
    if criterion == "D":
        return 2.0 * jnp.sum(jnp.log(jnp.diag(L)))
    return -jnp.trace(jax.scipy.linalg.cho_solve((L, True), jnp.eye(F.shape[0])))


def _info(G, chosen):
    """Σ_{chosen} G_iᵀ G_i: chosen is a 0/1 weight (M,)."""
    return jnp.einsum("i,imr,ims->rs", chosen, G, G)


@jit
def _greedy_exchange(G, k, prior, criterion, passes, nuisance=None):
    """Indices (k,) of a greedy + exchange design, its criterion value (with the `prior`
    information (r, r) added: a small ridge, or what earlier data already hold) and the
    number of accepted swaps. `nuisance`: a static tuple of indices, for "Ds"."""
    M, _, r = G.shape
    ridge = prior

    def add(j, state):
        chosen, order = state
        val = _objective(ridge + _info(G, chosen), G, criterion, nuisance)
        val = jnp.where(chosen > 0, -jnp.inf, val)
        i = jnp.argmax(val)
        return chosen.at[i].set(1.0), order.at[j].set(i)

    chosen, order = jax.lax.fori_loop(0, k, add, (jnp.zeros(M), jnp.zeros(k, dtype=int)))

    def swap(j, state):
        chosen, order, value, n = state
        out = order[j]
        base = chosen.at[out].set(0.0)
        val = _objective(ridge + _info(G, base), G, criterion, nuisance)
        val = jnp.where(base > 0, -jnp.inf, val)
        i = jnp.argmax(val)
        better = val[i] > value + 1e-10 * jnp.abs(value) + 1e-12
        i = jnp.where(better, i, out)
        return (
            base.at[i].set(1.0),
            order.at[j].set(i),
            jnp.where(better, val[i], value),
            n + better,
        )

    def one_pass(state):
        chosen, order, value, n, p, _ = state
        chosen, order, value, n2 = jax.lax.fori_loop(0, k, swap, (chosen, order, value, n))
        return chosen, order, value, n2, p + 1, n2 > n

    def again(state):
        return (state[4] < passes) & state[5]

    value = _value(ridge + _info(G, chosen), criterion, nuisance)
    state = (chosen, order, value, jnp.asarray(0), jnp.asarray(0), jnp.asarray(True))
    _, order, value, n, _, _ = jax.lax.while_loop(again, one_pass, state)
    return order, value, n


@dataclass(frozen=True)
class DesignQuality:
    """Quality of a design of K poses (criteria in column-scaled, identifiable coordinates).

    - `logdet`: log det F_S (−inf if F_S is singular on the identifiable directions);
    - `trace_inv`: trace F_S⁻¹ (inf if singular);
    - `o1`: (σ_1 ⋯ σ_r)^(1/r) / √K, `min_sv`: σ_r / √K, of the scaled Jacobian of the design;
    - `rank`: its numerical rank, of `r` directions the candidate set identifies;
    - `std` (P,): predicted parameter standard deviations (parameter units; inf for a
      direction the design or the candidate set cannot determine), `names` (P,),
      `nuisance` (P,) bool (instrument frame / target).
    """

    logdet: float
    trace_inv: float
    o1: float
    min_sv: float
    rank: int
    r: int
    std: np.ndarray
    names: list
    nuisance: np.ndarray

    @property
    def mean_std(self) -> float:
        """Mean predicted std of the non-nuisance parameters (their units: mm for the
        geometry; inf if one is undetermined)."""
        return float(np.mean(self.std[~self.nuisance]))


def _quality(jac: PoseJacobians, index, scale, V, tol: float) -> tuple[DesignQuality, np.ndarray]:
    index = np.asarray(index)
    K = len(index)
    Gs = ((jac.jac[index] / scale) @ V).reshape(-1, V.shape[1])
    sv = np.linalg.svd(Gs, compute_uv=False)
    r = V.shape[1]
    F = Gs.T @ Gs
    sign, logdet = np.linalg.slogdet(F)
    rank = int(np.sum(sv > tol * sv[0])) if sv.size else 0
    full = rank == r and sign > 0
    if full:
        Finv = np.linalg.inv(F)
        cov_scaled = V @ Finv @ V.T
        trace_inv = float(np.trace(Finv))
    else:
        cov_scaled = np.full((len(scale), len(scale)), np.inf)
        trace_inv = np.inf
    cov = cov_scaled / np.outer(scale, scale)
    std = np.sqrt(np.abs(np.diag(cov)))
    if V.shape[1] < V.shape[0]:  # parameters with weight outside the identifiable subspace
        out = 1.0 - np.sum(V**2, axis=1)
        std = np.where(out > 1e-6, np.inf, std)
    q = DesignQuality(
        logdet=float(logdet) if full else -np.inf,
        trace_inv=trace_inv,
        o1=float(np.exp(np.mean(np.log(sv[:r]))) / np.sqrt(K)) if full else 0.0,
        min_sv=float(sv[r - 1] / np.sqrt(K)) if len(sv) >= r else 0.0,
        rank=rank,
        r=r,
        std=std,
        names=jac.names,
        nuisance=jac.nuisance,
    )
    return q, cov


def evaluate_design(jac: PoseJacobians, index, *, tol: float = 1e-6) -> DesignQuality:
    """Criteria, observability indices and predicted parameter std of the design made of the
    candidates `index` (K,) (scaling and identifiable directions from all of `jac`)."""
    scale, V, _ = _reduce(jac.jac, tol)
    return _quality(jac, index, scale, V, tol)[0]


@dataclass(frozen=True)
class PoseSelection:
    """Chosen design: `index` (K,) into the candidates (in the order greedy chose them, as
    changed by the exchange passes), `poses` (K, 6), `quality` (DesignQuality), `criterion`,
    `swaps` (exchanges accepted), `covariance` (P, P) predicted parameter covariance."""

    index: np.ndarray
    poses: np.ndarray
    quality: DesignQuality
    criterion: str
    swaps: int
    covariance: np.ndarray


def select(
    jac: PoseJacobians,
    k: int,
    *,
    criterion: str = "D",
    exchange: bool = True,
    passes: int = 10,
    ridge: float = 1e-6,
    tol: float = 1e-6,
) -> PoseSelection:
    """Choose `k` distinct candidates of `jac` that optimise `criterion` ("D" or "A"; see the
    module docstring). `ridge`: ε = ridge × the mean per-pose information per direction,
    added as ε·I while searching (reported criteria are without it)."""
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {CRITERIA}, got {criterion!r}")
    M, m, _ = jac.jac.shape
    if not 1 <= k <= M:
        raise ValueError(f"k must be between 1 and the number of candidates ({M}), got {k}")
    scale, V, G = _reduce(jac.jac, tol)
    r = V.shape[1]
    if k * m < r:
        raise ValueError(
            f"{k} poses give {k * m} readings, fewer than the {r} identifiable parameter "
            f"directions: choose k >= {int(np.ceil(r / m))}"
        )
    eps = ridge * float(np.sum(G**2)) / (M * r)
    order, _, swaps = _greedy_exchange(
        device_array(G),
        int(k),
        device_array(eps * np.eye(r)),
        criterion,
        int(passes) if exchange else 0,
    )
    index = np.asarray(order)
    q, cov = _quality(jac, index, scale, V, tol)
    return PoseSelection(index, jac.poses[index], q, criterion, int(swaps), cov)


@one_blas_thread
def select_poses(
    nominal: Table,
    candidates,
    k: int,
    instrument: Instrument,
    free=DEFAULT_FREE,
    *,
    criterion: str = "D",
    exchange: bool = True,
    effects=None,
    compensated: bool = True,
    target=None,
    ridge: float = 1e-6,
) -> PoseSelection:
    """Choose `k` of the `candidates` (M, 6) (mm / rad) that make the calibration of `free`
    with `instrument` best determined: `select(pose_jacobians(...), k, ...)`."""
    jac = pose_jacobians(
        nominal,
        candidates,
        instrument,
        free,
        effects=effects,
        compensated=compensated,
        target=target,
    )
    return select(jac, k, criterion=criterion, exchange=exchange, ridge=ridge)


# --- what a design predicts for the pose error -----------------------------------------------


def pose_sensitivities(jac: PoseJacobians, poses) -> np.ndarray:
    """d pose / d θ (Q, 6, P) at commanded `poses` (Q, 6): how the pose the table reaches
    (for the nominal controller's commands) moves with each parameter of `jac` (zero for the
    nuisance frame / target), in the same parameterisation (gauge) as the fit."""
    poses = _check_poses(poses, "poses")
    data = Measurements(poses, poses.copy(), None, np.ones_like(poses))
    problem = make_problem(jac.nominal, data, jac.effects, jac.bases, jac.compensated)
    layout = Layout(tuple(jac.layout.free), (), (), 1, jac.layout.gauge)
    theta = zero_steps(jac.nominal, jac.effects, layout.free, jac.bases)
    S = jacobian_in_chunks(problem, layout, theta)[0].reshape(len(poses), 6, -1)
    out = np.zeros((len(poses), 6, len(jac.names)))
    out[:, :, ~jac.nuisance] = S
    return out


def _frame_target_jacobian(_, q):
    """d reading / d (frame, target) (6, 12) at platform pose `q` (6,), both at zero."""
    return jax.jacfwd(lambda ft: observe(q, ft[:6], ft[6:]))(jnp.zeros(12))


def rigid_projector(poses, radius: float) -> np.ndarray:
    """(Q·6, Q·6) projector that removes from pose errors at `poses` (Q, 6) the part a
    constant base-frame and platform-target transform explains (to first order), in the
    metric where an angle counts as its arc at `radius` mm. What is left is the error of the
    table's motion: what an instrument in an unknown frame, tracking an unknown target, can
    see, and what an IMU test (relative motions) depends on."""
    poses = _check_poses(poses, "poses")
    T = np.asarray(run_batch(_frame_target_jacobian, None, poses)).reshape(-1, 12)
    w = np.tile(np.array([1.0] * 3 + [radius] * 3), len(poses))
    Tw = T * w[:, None]
    # P = I − T (TᵀWᵀWT)⁻¹ TᵀWᵀW, written with the weighted T
    coef = np.linalg.lstsq(Tw, np.diag(w), rcond=None)[0]  # (12, Q·6)
    return np.eye(len(w)) - T @ coef


def align_pose_errors(poses, errors, radius: float) -> np.ndarray:
    """Pose errors (Q, 6) at `poses` (Q, 6) after removing the best constant base-frame and
    platform-target transform (see `rigid_projector`), mm / rad."""
    errors = np.asarray(errors, float)
    return (rigid_projector(poses, radius) @ errors.reshape(-1)).reshape(errors.shape)


def predicted_pose_error(covariance: np.ndarray, sensitivities: np.ndarray, projector=None):
    """RMS over poses of the predicted pose-error standard deviation per column (6,), mm /
    rad, from a parameter covariance (P, P) and sensitivities (Q, 6, P); with `projector`
    (from `rigid_projector`), of the error left after the best constant frame/target."""
    if not np.all(np.isfinite(covariance)):
        return np.full(6, np.inf)
    Q = sensitivities.shape[0]
    S = sensitivities.reshape(Q * 6, -1)
    if projector is not None:
        S = projector @ S
    var = np.einsum("kp,pr,kr->k", S, covariance, S).reshape(Q, 6)
    return np.sqrt(np.mean(np.clip(var, 0.0, None), axis=0))


@one_blas_thread
def compare_with_random(
    jac: PoseJacobians,
    k: int,
    *,
    n_random: int = 20,
    seed: int = 0,
    heldout=None,
    selection: PoseSelection | None = None,
    criterion: str = "D",
) -> dict:
    """Optimised vs random designs of `k` candidates of `jac`.

    Returns {"optimised": row, "random_median": row, "random": [row, ...], "selection"}
    where a row holds `logdet`, `o1`, `min_sv`, `mean_std` (geometric mean of the predicted
    std of the non-nuisance parameters), `pose_rms` (6,) (predicted pose-error RMS per
    column over `heldout` poses, default 200 random workspace poses, mm / rad) and `index`.
    The random designs are `n_random` uniform draws of k distinct candidates.
    """
    sel = select(jac, k, criterion=criterion) if selection is None else selection
    held = plan_random(200, seed=9_999) if heldout is None else _check_poses(heldout, "heldout")
    S = pose_sensitivities(jac, held)
    proj = rigid_projector(held, float(platform_radius(jac.nominal)))
    scale, V, _ = _reduce(jac.jac, 1e-6)
    rng = np.random.default_rng(seed)

    def row(index):
        q, cov = _quality(jac, index, scale, V, 1e-6)
        return {
            "index": np.asarray(index),
            "logdet": q.logdet,
            "trace_inv": q.trace_inv,
            "o1": q.o1,
            "min_sv": q.min_sv,
            "mean_std": q.mean_std,
            "pose_rms": predicted_pose_error(cov, S),
            "motion_rms": predicted_pose_error(cov, S, proj),
        }

    rand = [row(rng.choice(len(jac.poses), k, replace=False)) for _ in range(n_random)]
    med = {
        key: np.median(np.stack([np.asarray(r[key]) for r in rand]), axis=0)
        for key in ("logdet", "trace_inv", "o1", "min_sv", "mean_std", "pose_rms", "motion_rms")
    }
    return {"optimised": row(sel.index), "random_median": med, "random": rand, "selection": sel}
