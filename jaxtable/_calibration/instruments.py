"""Instruments: what a measuring device sees of the platform pose.

An instrument sits in its own frame F, the pose of the base frame expressed in F:
`frame` = (x, y, z, roll, pitch, yaw), so a base point p (relative to the home origin) is
R_F p + t_F in instrument coordinates. It tracks a target fixed on the platform at `target` =
(x, y, z, roll, pitch, yaw) in the platform frame. For ONE platform pose q it reads

    position     R_F (q_t + R(q) g_t) + t_F
    orientation  Euler Z-Y-X of R_F R(q) R(g_r)

and keeps the columns it measures: a 6-D tracker all six, a 3-D point tracker x, y, z, a
laser interferometer along x the x column only.
"""

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from .._batch import run_batch
from .._rotation import ARCSEC_PER_RAD, euler_from_matrix, rotation_matrix


def observe(pose, frame, target):
    """Full 6-D reading (mm, rad) of the target at platform pose `pose`; all (6,)."""
    R = rotation_matrix(pose[3:])
    RF = rotation_matrix(frame[3:])
    pos = RF @ (pose[:3] + R @ target[:3]) + frame[:3]
    ang = euler_from_matrix(RF @ R @ rotation_matrix(target[3:]))
    return jnp.concatenate([pos, ang])


def _reading_row(target, row):
    pose, frame = row
    return observe(pose, frame, target)


def readings(poses, frames, target):
    """Full readings (M, 6) of `target` (6,) at platform poses (M, 6) through instrument
    frames (M, 6): `observe` row by row, through `run_batch` (one compiled program per row
    bucket where the inputs are concrete, numpy out; a `vmap` inside a trace)."""
    return run_batch(_reading_row, target, (poses, frames))


@dataclass(frozen=True)
class Instrument:
    """A measuring device: `columns` (indices 0..5 of x, y, z, roll, pitch, yaw it reads),
    `noise` (6,) 1σ per column (mm, rad), `name`."""

    name: str
    columns: tuple
    noise: tuple

    @property
    def mask(self) -> np.ndarray:
        m = np.zeros(6, bool)
        m[list(self.columns)] = True
        return m


def tracker6(pos_sigma=0.005, ang_sigma=2 / ARCSEC_PER_RAD) -> Instrument:
    """A 6-D pose tracker (laser tracker with a 6-DOF probe): 5 µm, 2 arcsec by default."""
    return Instrument("tracker6", (0, 1, 2, 3, 4, 5), (pos_sigma,) * 3 + (ang_sigma,) * 3)


def point_tracker(pos_sigma=0.010) -> Instrument:
    """A 3-D point tracker following one target on the platform: x, y, z, 10 µm."""
    return Instrument("point3", (0, 1, 2), (pos_sigma,) * 3 + (np.nan,) * 3)


def interferometer(sigma=0.001) -> Instrument:
    """A laser interferometer along x, as in the paper's Fig. 9 (x column only), 1 µm."""
    return Instrument("interferometer", (0,), (sigma,) + (np.nan,) * 5)


INSTRUMENTS = {"tracker6": tracker6, "point3": point_tracker, "interferometer": interferometer}
