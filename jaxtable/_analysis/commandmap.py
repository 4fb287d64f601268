"""Workspace command maps: the compensated command, the passive spiral extension and
reachability at every pose of a grid, streamed in chunks so any grid size runs in bounded
memory (10⁸ poses: see the benchmark)."""

from dataclasses import dataclass

import numpy as np

from .._batch import stream_batch
from .._effects import Effects, resolve_effects
from .._errors import require_x64
from .._kinematics import spiral_extension, within_limits
from .._model import inverse_extension
from .._table import Table
from .workspaces import Grid, PoseList, workspace_slice


def _command_map_row(shared, pose):
    table, effects = shared
    s, _ = inverse_extension(table, effects, pose)
    return table.zero_lengths + s, spiral_extension(table, pose), within_limits(table, pose)


@dataclass(frozen=True)
class CommandMap:
    """Per-pose results of `command_map` with the grid's shape as leading dims (numpy,
    float32 to halve memory): command (..., 6) mm, spiral (..., 6) mm, reachable (...)."""

    grid: "Grid | PoseList"
    command: np.ndarray
    spiral: np.ndarray
    reachable: np.ndarray


def command_map(
    table: Table,
    grid: "Grid | PoseList | np.ndarray | None" = None,
    *,
    effects: Effects | None = None,
    keep: bool = False,
    chunk: int = 1 << 18,
    progress: bool = False,
):
    """Compensated command (the table's effects by default: the spiral term), passive spiral
    extension and reachability at every pose of `grid`, `chunk` poses at a time.

    Returns (CommandMap or None when `keep=False`, summary). The summary, over the reachable
    poses: per-leg command range (min, max) in mm, per-leg max |spiral extension| in mm, the
    largest |spiral extension| and the pose where it occurs. Peak memory is one chunk's work
    (about 100 bytes a pose) plus, with `keep`, 52 bytes a pose of results.
    """
    require_x64()
    if grid is None:
        grid = workspace_slice()
    elif not isinstance(grid, (Grid, PoseList)):
        grid = PoseList(np.asarray(grid, dtype=float).reshape(-1, 6))
    eff = resolve_effects(table, effects)
    n = len(grid)
    lo = np.full(6, np.inf)
    hi = np.full(6, -np.inf)
    spiral_max = np.zeros(6)
    worst = (0.0, None)
    n_reach = 0
    kept = [] if keep else None
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=n, unit="pose", desc=f"command map, {n} poses")
    parts = (grid.poses(start, start + chunk) for start in range(0, n, chunk))
    # the next chunks compute while this loop reduces the finished one (`stream_batch`)
    for p, (cmd, spiral, reach) in stream_batch(_command_map_row, (table, eff), parts, chunk=chunk):
        if keep:
            kept.append((cmd.astype(np.float32), spiral.astype(np.float32), reach))
        if reach.any():
            c, a = cmd[reach], np.abs(spiral[reach])
            lo = np.minimum(lo, c.min(axis=0))
            hi = np.maximum(hi, c.max(axis=0))
            spiral_max = np.maximum(spiral_max, a.max(axis=0))
            k = int(np.argmax(a.max(axis=1)))
            if a[k].max() > worst[0]:
                worst = (float(a[k].max()), p[reach][k])
            n_reach += int(reach.sum())
        if bar is not None:
            bar.update(len(p))
    if bar is not None:
        bar.close()
    summary = {
        "poses": n,
        "reachable": n_reach,
        "command_min_mm": lo.tolist(),
        "command_max_mm": hi.tolist(),
        "spiral_max_mm": spiral_max.tolist(),
        "spiral_worst_mm": worst[0],
        "spiral_worst_pose": None if worst[1] is None else np.asarray(worst[1]).tolist(),
    }
    if not keep:
        return None, summary
    cat = [np.concatenate(x) for x in zip(*kept)]
    shp = grid.shape
    return CommandMap(grid, *(c.reshape(shp + c.shape[1:]) for c in cat)), summary
