"""Workspace descriptions: the ranges a table is asked to cover (`Workspace`), and the pose
sets analyses stream over (`Grid`, `PoseList`, `workspace_slice`)."""

import itertools
import math
from dataclasses import dataclass

import equinox as eqx
import numpy as np

from .._errors import POSE_COLUMNS
from .._params import pose_from_file


class Workspace(eqx.Module):
    """Ranges in mm / deg (as written in files and tables).

    - `single`: (6,) half-range of each DOF moved alone (x, y, z, roll, pitch, yaw);
    - `combined`: (6,) half-widths of the box all six DOF share when moved together.

    The default is the reference table's (README): x, y ±200 mm, z ±100 mm, roll, pitch ±15°,
    yaw ±20° alone; x, y ±100 mm, z ±50 mm, roll, pitch ±7.5°, yaw ±10° together.
    """

    single: tuple = eqx.field(static=True, default=(200.0, 200.0, 100.0, 15.0, 15.0, 20.0))
    combined: tuple = eqx.field(static=True, default=(100.0, 100.0, 50.0, 7.5, 7.5, 10.0))

    @staticmethod
    def to_internal(values) -> np.ndarray:
        """mm/deg -> mm/rad."""
        return pose_from_file(values)

    def sweeps(self, n: int = 41) -> np.ndarray:
        """Each DOF alone over its range: (6, n, 6) poses, mm/rad."""
        ranges = self.to_internal(self.single)
        s = np.linspace(-1, 1, n)
        return np.stack([np.outer(s, np.eye(6)[k] * ranges[k]) for k in range(6)])

    def box_samples(self, n_random: int = 20000, seed: int = 0, levels: int = 3) -> np.ndarray:
        """The combined box: its `levels`^6 grid (3: corners, edge and face midpoints, centre;
        2: corners) and `n_random` uniform samples, (levels^6 + n_random, 6), mm/rad."""
        box = self.to_internal(self.combined)
        grid = np.array(list(itertools.product(np.linspace(-1.0, 1.0, levels), repeat=6))) * box
        rnd = np.random.default_rng(seed).uniform(-1, 1, (n_random, 6)) * box
        return np.concatenate([grid, rnd])

    def describe(self) -> str:
        def fmt(v):
            return ", ".join(
                f"{c} ±{x:g} {'mm' if k < 3 else 'deg'}"
                for k, (c, x) in enumerate(zip(POSE_COLUMNS, v))
            )

        return f"each DOF alone: {fmt(self.single)}; all together: {fmt(self.combined)}"


@dataclass(frozen=True)
class Grid:
    """A regular grid over some pose DOF, the others fixed; poses made chunk by chunk so a
    10⁷-pose grid never exists in memory at once.

    `axes`: indices (0..5) of the gridded DOF; `values`: one 1-D array per axis (mm / rad);
    `fixed`: (6,) pose for the other DOF.
    """

    axes: tuple
    values: tuple
    fixed: tuple

    @property
    def shape(self) -> tuple:
        return tuple(len(v) for v in self.values)

    def __len__(self) -> int:
        return math.prod(self.shape)

    def poses(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        stop = len(self) if stop is None else min(stop, len(self))
        idx = np.unravel_index(np.arange(start, stop), self.shape)
        out = np.tile(np.asarray(self.fixed, dtype=float), (stop - start, 1))
        for ax, vals, i in zip(self.axes, self.values, idx):
            out[:, ax] = np.asarray(vals)[i]
        return out


@dataclass(frozen=True)
class PoseList:
    """An explicit list of poses (N, 6) (mm / rad) with the `Grid` interface."""

    array: np.ndarray

    @property
    def shape(self) -> tuple:
        return (len(self.array),)

    def __len__(self) -> int:
        return len(self.array)

    def poses(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        return np.asarray(self.array[start:stop], dtype=float)


def workspace_slice(dofs=("x", "y"), n=101, ranges=None, fixed=None) -> Grid:
    """A 2-D (or n-D) slice: `dofs` names from x, y, z, roll, pitch, yaw; `n` points per axis;
    `ranges` half-ranges in mm / deg (default: the single-DOF workspace ranges);
    `fixed` the other DOF (mm / deg, default home)."""
    axes = []
    for d in dofs:
        if d not in POSE_COLUMNS:
            raise ValueError(f"unknown pose DOF '{d}'; use {', '.join(POSE_COLUMNS)}")
        axes.append(POSE_COLUMNS.index(d))
    if len(set(axes)) != len(axes):
        raise ValueError(f"repeated DOF in slice {dofs}")
    single = Workspace.to_internal(Workspace().single)
    if ranges is None:
        half = [single[a] for a in axes]
    else:
        half = [float(r) if a < 3 else math.radians(float(r)) for a, r in zip(axes, ranges)]
    ns = [n] * len(axes) if np.ndim(n) == 0 else list(n)
    if len(ns) != len(axes) or any(int(k) != k or k < 2 for k in ns):
        raise ValueError(
            f"n: points per slice axis, a whole number of at least 2 for each of {len(axes)} "
            f"axes; got {n}"
        )
    ns = [int(k) for k in ns]
    values = tuple(tuple(np.linspace(-h, h, k)) for h, k in zip(half, ns))
    fx = tuple(np.zeros(6) if fixed is None else Workspace.to_internal(fixed))
    return Grid(tuple(axes), values, fx)


class WorkspaceFileError(ValueError):
    """A workspace file is unreadable or has a bad value (the message names it)."""


def load_workspace(path) -> "Workspace | PoseList":
    """A required workspace from a file, mm / deg:

    - TOML with `single = [6 half-ranges]` (each DOF alone) and/or `combined = [6 half-widths]`
      (the box all DOF share), missing keys defaulting to the reference table's;
    - CSV with a header naming the pose columns x, y, z, roll, pitch, yaw (or cmd_x, ...):
      an explicit pose list; read as measurement files are (`_io.read_delimited`: UTF-8,
      comma, semicolon or tab; rows numbered from the line after the header); blank lines
      are skipped.
    """
    from pathlib import Path

    path = Path(path)
    if path.suffix.lower() == ".csv":
        from .._io import read_delimited

        header, rows = read_delimited(path, WorkspaceFileError, "workspace")
        if not header:
            raise WorkspaceFileError(f"{path}: empty file")
        header = [h.strip() for h in header]
        cols = []
        for c in POSE_COLUMNS:
            for name in (c, f"cmd_{c}"):
                if name in header:
                    cols.append(header.index(name))
                    break
            else:
                raise WorkspaceFileError(f"{path}: no column '{c}' (or 'cmd_{c}') in the header")
        poses = []
        for r, row in enumerate(rows, start=1):  # row 1: the line after the header
            if not any(cell.strip() for cell in row):
                continue
            values = []
            for c, k in zip(POSE_COLUMNS, cols):
                try:
                    values.append(float(row[k]))
                except (ValueError, IndexError):
                    cell = row[k] if k < len(row) else ""
                    raise WorkspaceFileError(
                        f"{path}: row {r}, column '{header[k]}': '{cell}' is not a number"
                    ) from None
                if not math.isfinite(values[-1]):
                    raise WorkspaceFileError(f"{path}: row {r}, column '{header[k]}' is not finite")
            poses.append(values)
        if not poses:
            raise WorkspaceFileError(f"{path}: no poses")
        return PoseList(pose_from_file(np.array(poses)))
    from .._io import read_toml

    doc = read_toml(path, WorkspaceFileError, "workspace")
    unknown = sorted(set(doc) - {"single", "combined"})
    if unknown:
        raise WorkspaceFileError(f"{path}: unknown key(s) {unknown}; use single, combined")
    values = {}
    for key in ("single", "combined"):
        if key not in doc:
            continue
        v = doc[key]
        if not isinstance(v, list) or len(v) != 6:
            raise WorkspaceFileError(
                f"{path}: '{key}' must be 6 numbers (x, y, z mm; roll, pitch, yaw deg); got {v!r}"
            )
        for c, x in zip(POSE_COLUMNS, v):
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not x >= 0:
                raise WorkspaceFileError(f"{path}: '{key}' {c} must be a number >= 0; got {x!r}")
        values[key] = tuple(float(x) for x in v)
    return Workspace(**values)
