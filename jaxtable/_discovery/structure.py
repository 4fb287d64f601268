"""A structure test that does not trust σ: do the residuals of stops that are close to each
other agree more than the noise allows?

After a fit, pure measurement noise leaves residuals e = (I − H) ε: no two stops share
anything but what the projection (I − H) puts between them. An effect the model lacks is a
smooth function of something the stops have in common — the legs' extensions, the direction
they travelled, the time they were measured, the temperature — so stops that are neighbours
in that variable have residuals that point the same way. The statistic of a feature family f
is the neighbour agreement

    A_f = Σ_i Σ_{j ∈ NN_k(i)} e_i · e_j / (k Σ_i |e_i|²)

(e_i the row's whitened residual vector, NN_k(i) its k nearest other stops in the family's
feature space). A_f is a ratio: any common scale of σ cancels, so a σ stated 25 % too small
or too large changes nothing; the relative scale of the noise groups (positions, angles,
instruments) is re-estimated from the fit's own residuals (variance-component estimation)
before the test, and the correlation between the columns of one row is estimated from the
residuals too, so a tracker whose x and pitch noise are correlated raises no alarm.

Null law: the same statistics for Monte Carlo residuals (I − H) z, z drawn with that
correlation and masked like the data (H the hat matrix of the fit's weighted Jacobian, the
linearisation of the fitted model: exact for a linear model with Gaussian noise). The
families are combined by the largest standardised statistic max_f (A_f − mean_f) / std_f,
whose null law comes from the same draws, so the test's false-alarm rate is `alpha` for the
whole family set (not per family).
"""

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from .._calibration.fit import Calibration, Setup
from .._calibration.noise import fit_basis, group_scales, redundancy
from .._threads import one_blas_thread

# feature families: the words a report uses for each
FAMILIES = {
    "extensions": "the legs' extensions",
    "extensions, direction": "the legs' extensions and direction of travel",
    "time": "time (neighbouring stops of a session)",
    "temperature": "temperature",
}


NEIGHBOURS = 3  # k of the k-nearest-neighbour agreement statistic (`structure_test`)


class TooFewRowsError(ValueError):
    """The structure test needs more fitted rows than the data have."""


def enough_rows(n: int, neighbours_k: int = NEIGHBOURS) -> bool:
    """Whether `n` rows are enough for the structure test: each needs `neighbours_k`
    neighbours and one row more to compare with."""
    return n > neighbours_k + 1


@dataclass(frozen=True)
class StructureTest:
    """Outcome of `structure_test`.

    - `p_value`: of the family-wise statistic (max standardised agreement); `structure`:
      p_value < alpha; `alpha`: the false-alarm rate;
    - `families`: {family: {"agreement": A_f, "null_mean", "null_std", "z", "p_value"}};
    - `hints`: families whose own p-value is below alpha, strongest first (what the
      residuals depend on: a structure seen but not necessarily named);
    - `draws`, `neighbours`: Monte Carlo draws and k.
    """

    p_value: float
    alpha: float
    families: dict
    hints: tuple
    draws: int
    neighbours: int

    @property
    def structure(self) -> bool:
        return bool(self.p_value < self.alpha)

    def words(self) -> str:
        if not self.structure:
            return (
                f"no structure seen: neighbouring stops' residuals agree no more than noise "
                f"(p = {self.p_value:.3g})"
            )
        hints = ", ".join(FAMILIES[h] for h in self.hints) or "no single family"
        return (
            f"structure remains (p = {self.p_value:.3g}): residuals of stops close in "
            f"{hints} agree more than noise allows"
        )

    def as_json(self) -> dict:
        return {
            "test": "neighbour agreement of whitened residuals against (I - H) z Monte Carlo; "
            "independent of the scale of sigma",
            "p_value": self.p_value,
            "alpha": self.alpha,
            "structure": self.structure,
            "hints": list(self.hints),
            "families": self.families,
            "draws": self.draws,
            "neighbours": self.neighbours,
        }


def features(st: Setup) -> dict:
    """Feature matrices {family: (N, F)} of the stops of a set-up (families whose variable
    does not vary are left out)."""
    problem = st.problem
    s = np.asarray(problem.s)
    ctx = problem.ctx
    scale = np.std(s) if np.std(s) > 0 else 1.0
    ext = s / scale
    out = {"extensions": ext}
    d = np.asarray(ctx.direction)
    if np.ptp(d) > 0:
        # a reversal on one leg weighs like two standard deviations of extension
        out["extensions, direction"] = np.concatenate([ext, d], axis=1)
    session = np.asarray(ctx.session)
    out["time"] = np.stack([clock_rows(ctx.time), 1e9 * session], axis=1)
    temperature = np.asarray(ctx.temperature, float)
    if np.ptp(temperature) >= 0.5:
        out["temperature"] = temperature[:, None]
    return out


def clock_rows(time) -> np.ndarray:
    """(N,) the stops' time (`Context.time`, 0..1 over the file) in units of the mean step
    between rows: the row index itself where the time is the row order (no `time` column),
    so that equal steps tie exactly; the clock's readings where the file logs them, so that
    stops on either side of a pause are not neighbours."""
    t = np.asarray(time, float)
    rows = np.arange(len(t), dtype=float)
    scaled = t * max(len(t) - 1, 1)
    return rows if np.allclose(scaled, rows, rtol=0, atol=1e-9) else scaled


def neighbours(x: np.ndarray, k: int, rows: np.ndarray) -> np.ndarray:
    """(R, k) indices (into `rows`) of the k nearest other rows of each of `rows` in feature
    space x (N, F), by a k-d tree (scipy's `cKDTree`): O(R log R) where a distance matrix
    is O(R²) (a 10,000-stop calibration spent 18 of its 25 s there). Each row's k + 1
    nearest are found and the row itself dropped; where more than k other rows tie with it
    at distance 0 (a stop repeated), the first k of them."""
    xr = np.asarray(x, float)[rows]
    idx = cKDTree(xr).query(xr, k + 1)[1]
    other = idx != np.arange(len(xr))[:, None]
    first = np.argsort(~other, axis=1, kind="stable")[:, :k]
    return np.take_along_axis(idx, first, axis=1)


def _agreement(e: np.ndarray, nn: np.ndarray):
    """A for residuals e (..., R, C) and neighbour indices nn (R, k). The sum runs over the k
    neighbour ranks, gathering one copy of e at a time: gathering all k at once made a
    (..., R, k, C) array (100 Monte Carlo draws of 10,000 stops: 144 MB), ~2× slower."""
    k = nn.shape[1]
    num = sum(np.einsum("...rc,...rc->...", e, e[..., nn[:, j], :]) for j in range(k))
    return num / (k * np.einsum("...rc,...rc->...", e, e))


@dataclass(frozen=True)
class Whitened:
    """The residuals of a fit in the form both tests use: `e` (N, 6) whitened residuals,
    each noise group rescaled to unit variance by VCE (0 where not fitted); `factor` (N, 6)
    the rescaling (applied to Jacobian rows too); `U` (N·6, r) orthonormal basis of the fit's
    column space (H = U Uᵀ); `L` (6, 6) Cholesky factor of the within-row correlation of
    the residuals; `mask` (N, 6) fitted cells; `rows` fitted rows; `dof`: Σ redundancy."""

    e: np.ndarray
    factor: np.ndarray
    U: np.ndarray
    L: np.ndarray
    mask: np.ndarray
    rows: np.ndarray
    dof: float

    def null_draws(self, draws: int, seed: int, batch: int = 100):
        """Batches (b, N, 6) of Monte Carlo null residuals (I − H) z, z with the rows'
        correlation, masked like the data."""
        rng = np.random.default_rng(seed)
        n = len(self.mask)
        for start in range(0, draws, batch):
            b = min(batch, draws - start)
            z = (rng.standard_normal((b, n, 6)) @ self.L.T * self.mask).reshape(b, -1)
            yield (z - (z @ self.U) @ self.U.T).reshape(b, n, 6)


def whitened(cal: Calibration, st: Setup, tol: float = 1e-6, vce: bool = True) -> Whitened:
    """`Whitened` of fit `cal` of set-up `st`; `vce=False`: the fit's weights as they are
    (σ as stated), without rescaling the noise groups to what the residuals show."""
    mask = np.asarray(st.mask) & (np.asarray(cal.weight) > 0)
    rows = np.flatnonzero(mask.any(axis=1))
    J = np.asarray(cal.jacobian)
    # relative scale of the noise groups from the fit itself (VCE), applied to the
    # residuals and the Jacobian alike
    groups = np.asarray(st.noise.groups) if st.noise is not None else np.where(mask, 0, -1)
    red = redundancy(J, tol)
    scale, _ = group_scales(cal.residual, red, groups, mask)
    if not vce:
        scale = np.ones_like(scale)
    factor = np.where(mask, 1.0 / scale[np.maximum(groups, 0)], 0.0)
    e = np.where(mask, np.asarray(cal.residual), 0.0) * factor
    U = fit_basis(J * factor.reshape(-1, 1), tol)  # (N·6, r) orthonormal
    # within-row correlation of the noise, from fully measured rows' residuals
    full = mask[rows].all(axis=1)
    C = np.eye(6)
    if full.sum() >= 30:
        C = np.corrcoef(e[rows][full], rowvar=False)
    L = np.linalg.cholesky(C + 1e-9 * np.eye(6))
    return Whitened(e, factor, U, L, mask, rows, float(red[mask.reshape(-1)].sum()))


@dataclass(frozen=True)
class NullLaw:
    """Null law of the family-wise statistic for one fit's projection: per family the
    Monte Carlo agreements `null` {family: (draws,) A_f}, their mean and std, and `zmax`
    (draws,) the largest standardised agreement of each draw."""

    mean: dict
    std: dict
    null: dict

    @cached_property
    def zmax(self) -> np.ndarray:
        return np.sort(self.z(self.null))

    def z(self, observed: dict) -> np.ndarray:
        """Largest standardised agreement max_f (A_f − mean_f) / std_f of `observed`
        {family: A_f (...,)}."""
        return np.asarray(
            np.max([(observed[f] - self.mean[f]) / self.std[f] for f in self.mean], axis=0)
        )

    def p_value(self, zmax: np.ndarray) -> np.ndarray:
        """Monte Carlo p-value (1 + #{null ≥ z}) / (draws + 1) of `zmax` (...,)."""
        srt = self.zmax
        above = len(srt) - np.searchsorted(srt, np.asarray(zmax), side="left")
        return np.asarray((1.0 + above) / (len(srt) + 1.0))


def null_law(w: Whitened, nns: dict, draws: int, seed: int, Q=None) -> NullLaw:
    """`NullLaw` of residuals (I − H) z of fit `w` (`Whitened.null_draws`), or of
    (I − H − Q Qᵀ) z with `Q` (N·6, q) orthonormal and orthogonal to the fit's column space:
    the fit with q more columns, linearised; `nns` {family: (R, k) neighbours of w.rows}."""
    null = {f: [] for f in nns}
    for z in w.null_draws(draws, seed):
        if Q is not None:
            flat = z.reshape(len(z), -1)
            z = (flat - (flat @ Q) @ Q.T).reshape(z.shape)
        for f, nn in nns.items():
            null[f].append(_agreement(z[:, w.rows], nn))
    null = {f: np.concatenate(v) for f, v in null.items()}
    mean = {f: float(v.mean()) for f, v in null.items()}
    std = {f: float(v.std()) if v.std() > 0 else 1.0 for f, v in null.items()}
    return NullLaw(mean, std, null)


def agreements(w: Whitened, nns: dict, e: np.ndarray | None = None) -> dict:
    """{family: A_f} of whitened residuals `e` (..., N, 6) (default the fit's own)."""
    e = w.e if e is None else e
    return {f: _agreement(e[..., w.rows, :], nn) for f, nn in nns.items()}


@one_blas_thread
def structure_test(
    cal: Calibration,
    st: Setup,
    *,
    alpha: float = 0.01,
    draws: int = 1000,
    neighbours_k: int = NEIGHBOURS,
    seed: int = 0,
    tol: float = 1e-6,
) -> StructureTest:
    """Test the residuals of fit `cal` (of set-up `st`) for structure, without trusting σ's
    scale (see the module docstring). `alpha`: false-alarm rate; `draws`: Monte Carlo draws
    of the null law (p-value resolution 1/(draws + 1)); `neighbours_k`: k; `seed`: of the
    draws."""
    w = whitened(cal, st, tol)
    rows = w.rows
    if not enough_rows(len(rows), neighbours_k):
        raise TooFewRowsError(
            f"the structure test needs more than {neighbours_k + 1} fitted rows; {len(rows)} here"
        )

    feats = features(st)
    nns = {f: neighbours(x, neighbours_k, rows) for f, x in feats.items()}
    observed = {f: float(a) for f, a in agreements(w, nns).items()}
    law = null_law(w, nns, draws, seed)
    stats = {
        f: {
            "agreement": observed[f],
            "null_mean": law.mean[f],
            "null_std": law.std[f],
            "z": float((observed[f] - law.mean[f]) / law.std[f]),
            "p_value": float((1 + np.sum(law.null[f] >= observed[f])) / (draws + 1)),
        }
        for f in feats
    }
    p = float(law.p_value(law.z(observed)))
    hints = tuple(
        sorted((f for f in stats if stats[f]["p_value"] < alpha), key=lambda f: -stats[f]["z"])
    )
    return StructureTest(p, alpha, stats, hints, draws, neighbours_k)
