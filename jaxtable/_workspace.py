"""Workspace descriptions: the ranges a table is asked to cover, and pose sets over them."""

import itertools

import equinox as eqx
import numpy as np

from ._errors import POSE_COLUMNS


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
        out = np.array(values, dtype=float)
        out[..., 3:] = np.deg2rad(out[..., 3:])
        return out

    def sweeps(self, n: int = 41) -> np.ndarray:
        """Each DOF alone over its range: (6, n, 6) poses, mm/rad."""
        ranges = self.to_internal(self.single)
        s = np.linspace(-1, 1, n)
        return np.stack([np.outer(s, np.eye(6)[k] * ranges[k]) for k in range(6)])

    def box_samples(self, n_random: int = 20000, seed: int = 0) -> np.ndarray:
        """The combined box: its 3^6 grid of corners/edge midpoints and `n_random` uniform
        samples, (729 + n_random, 6), mm/rad."""
        box = self.to_internal(self.combined)
        grid = np.array(list(itertools.product([-1.0, 0.0, 1.0], repeat=6))) * box
        rnd = np.random.default_rng(seed).uniform(-1, 1, (n_random, 6)) * box
        return np.concatenate([grid, rnd])

    def describe(self) -> str:
        def fmt(v):
            return ", ".join(
                f"{c} ±{x:g} {'mm' if k < 3 else 'deg'}"
                for k, (c, x) in enumerate(zip(POSE_COLUMNS, v))
            )

        return f"each DOF alone: {fmt(self.single)}; all together: {fmt(self.combined)}"
