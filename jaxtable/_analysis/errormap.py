"""Workspace error maps: pose-error standard deviation per error source at every pose of a
grid, linear propagation of a tolerance budget, evaluated in bounded-memory chunks.

Per pose (one-pose function `budget_one`, batched with vmap):
- `std` (n_sources + 1, 6): σ of each pose component (x, y, z mm; rotation vector rad) per
  source, last row the total (sources independent);
- `bias` (6,): pose error of a controller that does NOT compensate the passive spiral term
  (linearised: J⁻¹ Δl2; the exact value is within ~1 % of it, see studies/paper_spiral.py);
- `cond`: condition number of the kinematic Jacobian (angles scaled by the platform radius);
- `reachable`: legs inside the stroke and U-joints within their bend limit.

The sensitivities are closed form (`sensitivities.budget_jacobians_one`); the streamed
summary's RMS errors and their histogram bins are computed per pose in the same kernel, so
the host only counts bins.
"""

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from .._batch import stream_batch
from .._errors import require_x64
from .._forward import platform_radius
from .._kinematics import within_limits
from .._linalg import cond_of_gram, gram_small, inv_normal_small, matmul_small
from .._rotation import ARCSEC_PER_RAD, euler_rate_matrix
from .._table import Table
from .sensitivities import BUDGET_WRT, budget_jacobians_one
from .tolerances import PARAMETER, SOURCES, Tolerances
from .workspaces import Grid, PoseList, workspace_slice

TARGET_MM = 0.2  # the paper's design target: translation error within ±0.2 mm


def budget_one(table: Table, sigmas: tuple, pose, with_cond: bool = True):
    """Linear budget at one commanded pose; see the module docstring. `sigmas`: σ per source
    in model units, ordered as `SOURCES`. `with_cond=False`: cond is NaN (the 2-norm
    condition number, `_linalg.cond_small`, costs about as much as the rest of the budget)."""
    # closed-form blocks (sensitivities.budget_jacobians_one): the lead-scale error is zero
    # at the nominal and adds nothing to the command, so the command is explicit
    _, K, gains, spiral = budget_jacobians_one(table, pose)
    # δ(t, ω) = −K⁻¹ D δθ with D block-diagonal by leg: column (i, c) of the pose error is
    # −K⁻¹[:, i] · d_ic, so σ² = σ_src² Σ_i (K⁻¹[:, i])² Σ_c d_ic² (= gains[i, param]).
    # K⁻¹ = D (K D)⁻¹ with D = diag(1, 1, 1, 1/ρ, 1/ρ, 1/ρ): K D is well conditioned
    rho = platform_radius(table)
    d = jnp.array([1.0, 1.0, 1.0, 1.0 / rho, 1.0 / rho, 1.0 / rho])
    Kd = K * d
    Kinv = d[:, None] * inv_normal_small(Kd)
    column = [BUDGET_WRT.index(PARAMETER[src]) for src in SOURCES]
    std = jnp.asarray(sigmas)[:, None] * jnp.sqrt(matmul_small(Kinv**2, gains[:, column])).T
    std = jnp.concatenate([std, jnp.sqrt(jnp.sum(std**2, axis=0))[None]])
    bias = matmul_small(Kinv, spiral)  # not compensating = an L0 error of Δl2
    if with_cond:
        # of the Euler-angle Jacobian J = K D B, B = diag(I, E), angles scaled by the radius ρ:
        # from JᵀJ = Bᵀ G B with G = (K D)ᵀ(K D), the Gram matrix the inverse above forms
        # (one program computes it once), instead of J and its own Gram matrix (map ~5 %
        # faster)
        E = euler_rate_matrix(pose[3:])
        G = gram_small(Kd)
        low = matmul_small(E.T, G[3:, :3])  # the lower triangle is what cond_of_gram reads
        rot = matmul_small(E.T, matmul_small(G[3:, 3:], E))
        top = jnp.concatenate([G[:3, :3], low.T], axis=1)
        cond = cond_of_gram(jnp.concatenate([top, jnp.concatenate([low, rot], axis=1)]))
    else:
        cond = jnp.asarray(jnp.nan)
    reach = within_limits(table, pose, once=True)  # shares the budget's sines
    return std, bias, cond, reach


def _rms(std, bias, cols: slice):
    """RMS over the pose components `cols` of each source's σ, (..., n_sources + 1), and of
    the total with the spiral bias added (uncompensated), (...). numpy or jax arrays."""
    v = (std[..., cols] ** 2).sum(-1)
    return v**0.5, (v[..., -1] + (bias[..., cols] ** 2).sum(-1)) ** 0.5


def _margins(std, bias):
    """Worst translation component of 2σ (compensated) and of |bias| + 2σ (uncompensated),
    mm, (...) each. numpy or jax arrays."""
    m = 2 * std[..., -1, :3]
    return m.max(-1), (m + abs(bias[..., :3])).max(-1)


def _budget_row(shared, pose):
    """`budget_one` and what the streamed summary needs of it: the 2 × (n_sources + 2) RMS
    errors (translation mm, rotation arcsec) with their slots in the histograms
    (`_Histograms.slots`), and whether the two target margins are met, each for a reachable
    pose only (0, the dropped slot, False out of reach); the host then only counts slots.
    shared = (table, sigmas, with_cond, keep): without `keep` the per-pose σ and bias are
    not returned (None)."""
    table, sigmas, with_cond, keep = shared
    std, bias, cond, reach = budget_one(table, sigmas, pose, with_cond)
    tc, tu = _rms(std, bias, slice(0, 3))
    rc, ru = _rms(std, bias, slice(3, 6))
    values = jnp.stack([jnp.append(tc, tu), jnp.append(rc, ru) * ARCSEC_PER_RAD])
    ok = jnp.stack(_margins(std, bias)) <= TARGET_MM
    if not keep:
        std = bias = None
    # the summary's share, over reachable poses only, ready for the host to count without
    # indexing: the values (0 out of reach), their slots in the histograms, whether the
    # margins are met
    slots = _Histograms.slots(values, reach)
    return std, bias, cond, reach, jnp.where(reach, values, 0.0), slots, ok & reach


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
        return self._rms(slice(0, 3), compensated)

    def rotation(self, compensated: bool = True) -> np.ndarray:
        """(..., n_sources + 1) RMS rotation error per source (rad)."""
        return self._rms(slice(3, 6), compensated)

    def _rms(self, cols, compensated):
        per_source, uncompensated = _rms(self.std, self.bias, cols)
        if not compensated:
            per_source[..., -1] = uncompensated
        return per_source

    def target_margin(self, compensated: bool = True) -> np.ndarray:
        """(...,) worst translation component |bias| + 2σ (mm): ≤ 0.2 meets the paper's
        ±0.2 mm design target at about 95 % confidence per component."""
        return _margins(self.std, self.bias)[0 if compensated else 1]


class _Histograms:
    """Streaming log-binned histograms of positive values (one per row and column of the
    per-pose `values`), for percentiles: `bin_index` runs inside the kernel, `add` counts."""

    LO, HI, BINS = 1e-9, 1e3, 3000

    def __init__(self, shape: tuple):
        self.edges = np.geomspace(self.LO, self.HI, self.BINS + 1)
        self.counts = np.zeros(shape + (self.BINS + 2,), dtype=np.int64)
        self.max = np.zeros(shape)

    @classmethod
    def bin_index(cls, x):
        """`np.searchsorted(edges, x)` (the number of edges below x; 0 below LO, BINS + 1
        above HI or NaN) by arithmetic, as int32: jnp, for inside the kernel."""
        k = jnp.ceil(jnp.log(x / cls.LO) * (cls.BINS / np.log(cls.HI / cls.LO)))
        return jnp.where(jnp.isnan(k), cls.BINS + 1, jnp.clip(k, 0, cls.BINS + 1)).astype(jnp.int32)

    @classmethod
    def slots(cls, values, counted):
        """Where each of `values` (*shape) counts in the histograms' counts flattened
        (`bin_index` offset by its histogram's place), as int32: jnp, for inside the kernel.
        Where `counted` (a scalar) is False: one past the last count, a slot `add` drops."""
        m = cls.BINS + 2
        place = np.arange(np.size(values)).reshape(np.shape(values)) * m
        return jnp.where(counted, cls.bin_index(values) + place, np.size(values) * m).astype(
            jnp.int32
        )

    def add(self, values, slots):
        """Count one chunk: its values' slots (n, *shape; `slots`) and the `values` (n,
        *shape), 0 where not counted (for the maxima; the values are positive). The host's
        share of the streamed map: one bincount and one max over the chunk, no indexing
        (with the reachable rows picked out on the host first, counting took ~15 ms a chunk
        of 65,536 poses where this takes ~5, beside the kernel's ~60)."""
        if len(values):
            size = self.counts.size
            counts = np.bincount(slots.reshape(-1), minlength=size + 1)[:size]
            self.counts += counts.reshape(self.counts.shape)
            self.max = np.maximum(self.max, values.max(axis=0))

    def percentile(self, index: tuple, q) -> float:
        c = np.cumsum(self.counts[index])
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
    chunk: int = 1 << 16,
    progress: bool = False,
    cond: bool = True,
):
    """Propagate `tolerances` over every pose of `grid` in chunks of `chunk` poses.
    `cond=False` skips the condition number (NaN in the map and the summary): about half
    the work per pose, and no part of the budget.

    Returns (ErrorMap or None when `keep=False`, summary dict). The summary streams over the
    reachable poses: for every source and the totals (compensated, uncompensated), the max
    and 95th percentile of the RMS translation (mm) and rotation (arcsec) error, and the
    fraction of poses meeting the ±0.2 mm target. Peak memory is a few chunks' results (the
    next chunks compute while the last one is counted; about 200 bytes a pose) plus, with
    `keep`, the per-pose results (about 100 bytes a pose).
    """
    require_x64()
    if grid is None:
        grid = workspace_slice()
    elif not isinstance(grid, (Grid, PoseList)):
        grid = PoseList(np.asarray(grid, dtype=float).reshape(-1, 6))
    if len(grid) == 0:
        raise ValueError("error_map: the grid has no poses")
    # arrays, not Python floats: the compiled kernel takes them as arguments, so every
    # budget (a scaled one, another tolerance file) runs the same program instead of
    # compiling one with its numbers built in
    sigmas = tuple(np.asarray(s, dtype=np.float64) for s in tolerances.sigmas())
    names = list(SOURCES) + ["total", "total (spiral uncompensated)"]
    hist = _Histograms((2, len(names)))  # rows: translation mm, rotation arcsec
    n_reach = 0
    n_ok = np.zeros(2, dtype=np.int64)  # compensated, uncompensated
    cond_max = 0.0 if cond else float("nan")
    out = [] if keep else None
    n = len(grid)
    bar = tqdm(total=n, disable=not progress, unit="pose", desc=f"error map, {n} poses")
    parts = (grid.poses(start, start + chunk) for start in range(0, n, chunk))
    # the next chunks compute while this loop counts the finished one (`stream_batch`)
    for p, (std, bias, kappa, reach, values, slots, ok) in stream_batch(
        _budget_row, (table, sigmas, bool(cond), keep), parts, chunk=chunk
    ):
        if keep:
            out.append(tuple(x.astype(np.float32) for x in (std, bias, kappa)) + (reach,))
        hist.add(values, slots)  # values, slots and ok: of the reachable poses only
        n_reach += int(reach.sum())
        n_ok += ok.sum(axis=0)
        if cond and reach.any():
            cond_max = max(cond_max, float(np.max(kappa, where=reach, initial=0.0)))
        bar.update(len(p))
    bar.close()
    summary = {
        "poses": n,
        "reachable": n_reach,
        "cond_max": cond_max,
        "target_mm": TARGET_MM,
        "meets_target_compensated": int(n_ok[0]) / max(n_reach, 1),
        "meets_target_uncompensated": int(n_ok[1]) / max(n_reach, 1),
        "sources": {
            name: {
                "trans_max_mm": float(hist.max[0, k]),
                "trans_p95_mm": hist.percentile((0, k), 95),
                "rot_max_arcsec": float(hist.max[1, k]),
                "rot_p95_arcsec": hist.percentile((1, k), 95),
            }
            for k, name in enumerate(names)
        },
    }
    if not keep:
        return None, summary
    cat = [np.concatenate(x) for x in zip(*out)]
    shp = grid.shape
    emap = ErrorMap(grid, *(c.reshape(shp + c.shape[1:]) for c in cat))
    return emap, summary
