"""Workspace error maps: pose-error standard deviation per error source at every pose of a
grid, linear propagation of a tolerance budget, evaluated in bounded-memory chunks.

Per pose (one-pose function `budget_one`, batched with vmap):
- `std` (n_sources + 1, 6): σ of each pose component (x, y, z mm; rotation vector rad) per
  source, last row the total (sources independent);
- `bias` (6,): pose error of a controller that does NOT compensate the passive spiral term
  (linearised: J⁻¹ Δl2; the exact value is within ~1 % of it, see studies/paper_spiral.py);
- `cond`: condition number of the kinematic Jacobian (angles scaled by the platform radius);
- `reachable`: legs inside the stroke and U-joints within their bend limit.
"""

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from .. import _params as params
from .._batch import run_batch
from .._errors import require_x64
from .._forward import platform_radius
from .._kinematics import spiral_extension, within_limits
from .._linalg import cond_small, inv_small
from .._model import inverse_extension
from .._rotation import ARCSEC_PER_RAD, euler_rate_matrix
from .._table import Table
from .sensitivities import per_leg_jacobians_one
from .tolerances import PARAMETER, SOURCES, Tolerances, budget_effects
from .workspaces import Grid, PoseList, workspace_slice

BUDGET_WRT = params.GEOMETRY + ("lead_scale.eps", "spiral.lead")
TARGET_MM = 0.2  # the paper's design target: translation error within ±0.2 mm


def budget_one(table: Table, sigmas: tuple, pose, with_cond: bool = True):
    """Linear budget at one commanded pose; see the module docstring. `sigmas`: σ per source
    in model units, ordered as `SOURCES`. `with_cond=False`: cond is NaN (the 2-norm
    condition number costs three times the rest of the budget)."""
    effects = budget_effects(table)
    # the lead-scale error is zero at the nominal: it adds nothing to the command, so the
    # command is explicit (no Newton iteration for an s-dependent effect)
    s, _ = inverse_extension(table, {"spiral": effects["spiral"]}, pose)
    Jq, per_leg = per_leg_jacobians_one(table, effects, pose, BUDGET_WRT, s)
    # δq = −Jq⁻¹ D δθ with D block-diagonal by leg: column (i, c) of δq/δθ is
    # −Jq⁻¹[:, i] · d_ic, so σ_q² = σ² Σ_i (Jq⁻¹[:, i])² Σ_c d_ic².
    Jinv = inv_small(Jq)  # plain jnp: see _linalg on LAPACK deadlocks
    Jinv = jnp.concatenate([Jinv[:3], euler_rate_matrix(pose[3:]) @ Jinv[3:]])
    leg_gain = dict(zip(BUDGET_WRT, (jnp.sum(d**2, axis=1) for d in per_leg)))
    rows = [
        sigma * jnp.sqrt(Jinv**2 @ leg_gain[PARAMETER[src]]) for src, sigma in zip(SOURCES, sigmas)
    ]
    std = jnp.stack(rows)
    std = jnp.concatenate([std, jnp.sqrt(jnp.sum(std**2, axis=0))[None]])
    bias = Jinv @ spiral_extension(table, pose)  # not compensating = an L0 error of Δl2
    scale = jnp.concatenate([jnp.ones(3), jnp.full(3, 1.0 / platform_radius(table))])
    cond = cond_small(Jq * scale) if with_cond else jnp.asarray(jnp.nan)
    reach = within_limits(table, pose)
    return std, bias, cond, reach


def _budget_row(shared, pose):
    table, sigmas, with_cond = shared
    return budget_one(table, sigmas, pose, with_cond)


@dataclass(frozen=True)
class ErrorMap:
    """Result of `error_map`: per-pose arrays with the grid's shape as leading dims (numpy).

    std (..., n_sources + 1, 6); bias (..., 6); cond (...); reachable (...)."""

    grid: "Grid | PoseList"
    std: np.ndarray
    bias: np.ndarray
    cond: np.ndarray
    reachable: np.ndarray

    def translation(self, compensated: bool = True) -> np.ndarray:
        """(..., n_sources + 1) RMS translation error per source (mm); with
        `compensated=False` the total row includes the spiral bias."""
        t = np.sqrt(np.sum(self.std[..., :3] ** 2, axis=-1))
        if not compensated:
            t[..., -1] = np.sqrt(t[..., -1] ** 2 + np.sum(self.bias[..., :3] ** 2, axis=-1))
        return t

    def rotation(self, compensated: bool = True) -> np.ndarray:
        """(..., n_sources + 1) RMS rotation error per source (rad)."""
        r = np.sqrt(np.sum(self.std[..., 3:] ** 2, axis=-1))
        if not compensated:
            r[..., -1] = np.sqrt(r[..., -1] ** 2 + np.sum(self.bias[..., 3:] ** 2, axis=-1))
        return r

    def target_margin(self, compensated: bool = True) -> np.ndarray:
        """(...,) worst translation component |bias| + 2σ (mm): ≤ 0.2 meets the paper's
        ±0.2 mm design target at about 95 % confidence per component."""
        m = 2 * self.std[..., -1, :3]
        if not compensated:
            m = m + np.abs(self.bias[..., :3])
        return m.max(axis=-1)


class _Histogram:
    """Streaming log-binned histogram for percentiles of positive values."""

    def __init__(self, lo=1e-9, hi=1e3, bins=3000):
        self.edges = np.geomspace(lo, hi, bins + 1)
        self.counts = np.zeros(bins + 2, dtype=np.int64)
        self.max = 0.0

    def add(self, x):
        if x.size:
            self.counts += np.bincount(np.searchsorted(self.edges, x), minlength=self.counts.size)
            self.max = max(self.max, float(x.max()))

    def percentile(self, q):
        c = np.cumsum(self.counts)
        if c[-1] == 0:
            return float("nan")
        k = int(np.searchsorted(c, q / 100 * c[-1]))
        return float(self.edges[min(max(k, 1), len(self.edges) - 1)])


def error_map(
    table: Table,
    tolerances: Tolerances = Tolerances(),
    grid: "Grid | PoseList | np.ndarray | None" = None,
    *,
    keep: bool = True,
    chunk: int = 8192,
    progress: bool = False,
    cond: bool = True,
):
    """Propagate `tolerances` over every pose of `grid` in chunks of `chunk` poses.
    `cond=False` skips the condition number (NaN in the map and the summary): three quarters
    of the work per pose, and no part of the budget.

    Returns (ErrorMap or None when `keep=False`, summary dict). The summary streams over the
    reachable poses: for every source and the totals (compensated, uncompensated), the max
    and 95th percentile of the RMS translation (mm) and rotation (arcsec) error, and the
    fraction of poses meeting the ±0.2 mm target. Peak memory is one chunk's work plus, with
    `keep`, the per-pose results (about 100 bytes a pose).
    """
    require_x64()
    if grid is None:
        grid = workspace_slice()
    elif not isinstance(grid, (Grid, PoseList)):
        grid = PoseList(np.asarray(grid, dtype=float).reshape(-1, 6))
    sigmas = tuple(tolerances.sigma(s) for s in SOURCES)
    names = list(SOURCES) + ["total", "total (spiral uncompensated)"]
    hist_t = {n: _Histogram() for n in names}
    hist_r = {n: _Histogram() for n in names}
    n_reach = n_ok_c = n_ok_u = 0
    cond_max = 0.0 if cond else float("nan")
    out = [] if keep else None
    n = len(grid)
    for start in tqdm(
        range(0, n, chunk), disable=not progress, unit="chunk", desc=f"error map, {n} poses"
    ):
        p = grid.poses(start, start + chunk)
        std, bias, kappa, reach = (
            np.asarray(x)
            for x in run_batch(_budget_row, (table, sigmas, bool(cond)), p, chunk=chunk)
        )
        if keep:
            out.append(
                (std.astype(np.float32), bias.astype(np.float32), kappa.astype(np.float32), reach)
            )
        part = ErrorMap(grid, std[reach], bias[reach], kappa[reach], reach[reach])
        tc, tu = part.translation(True), part.translation(False)
        rc, ru = part.rotation(True), part.rotation(False)
        for k, name in enumerate(SOURCES + ("total",)):
            hist_t[name].add(tc[:, k])
            hist_r[name].add(rc[:, k] * ARCSEC_PER_RAD)
        hist_t[names[-1]].add(tu[:, -1])
        hist_r[names[-1]].add(ru[:, -1] * ARCSEC_PER_RAD)
        n_reach += int(reach.sum())
        n_ok_c += int((part.target_margin(True) <= TARGET_MM).sum())
        n_ok_u += int((part.target_margin(False) <= TARGET_MM).sum())
        if cond and reach.any():
            cond_max = max(cond_max, float(kappa[reach].max()))
    summary = {
        "poses": n,
        "reachable": n_reach,
        "cond_max": cond_max,
        "target_mm": TARGET_MM,
        "meets_target_compensated": n_ok_c / max(n_reach, 1),
        "meets_target_uncompensated": n_ok_u / max(n_reach, 1),
        "sources": {
            name: {
                "trans_max_mm": hist_t[name].max,
                "trans_p95_mm": hist_t[name].percentile(95),
                "rot_max_arcsec": hist_r[name].max,
                "rot_p95_arcsec": hist_r[name].percentile(95),
            }
            for name in names
        },
    }
    if not keep:
        return None, summary
    cat = [np.concatenate(x) for x in zip(*out)]
    shp = grid.shape
    emap = ErrorMap(grid, *(c.reshape(shp + c.shape[1:]) for c in cat))
    return emap, summary
