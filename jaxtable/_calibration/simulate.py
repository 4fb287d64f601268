"""Simulate a real table and its instrument: a "true" table (the nominal one plus sampled
geometric errors and chosen effects), a controller that commands the nominal inverse
kinematics, exact forward kinematics of the true table, and a noisy instrument."""

import numpy as np

from .._analysis.workspaces import Workspace
from .._api import actuator_command, forward
from .._batch import run_batch
from .._context import Context, batch_context, directions, run_time
from .._errors import renamed_argument
from .._jit import device_array
from .._table import Table, replace
from .instruments import Instrument, observe
from .measurements import Measurements

# --- pose plans (mm / rad, (N, 6)) ---------------------------------------------------------


def plan_x_line(step: float = 25.0, half: float = 200.0) -> np.ndarray:
    """The paper's Fig. 9 experiment: x from −half to +half every `step` mm."""
    xs = np.arange(-half, half + step / 2, step)
    p = np.zeros((len(xs), 6))
    p[:, 0] = xs
    return p


def plan_random(n: int, seed: int = 0, workspace: Workspace = Workspace()) -> np.ndarray:
    """`n` poses uniform in the workspace's combined-motion box."""
    box = Workspace.to_internal(workspace.combined)
    return np.random.default_rng(seed).uniform(-1, 1, (n, 6)) * box


def plan_grid(n: int = 3, workspace: Workspace = Workspace()) -> np.ndarray:
    """A full 6-D grid of `n` levels per DOF over the combined box (n^6 poses)."""
    box = Workspace.to_internal(workspace.combined)
    levels = np.linspace(-1, 1, n)
    g = np.stack(np.meshgrid(*[levels] * 6, indexing="ij"), -1).reshape(-1, 6)
    return g * box


def plan_swing(
    dof: str = "roll", amplitude: float = 5.0, cycles: float = 2.0, points: int = 80
) -> np.ndarray:
    """A sinusoidal swing of one DOF as an IMU test uses: `amplitude` in mm or deg."""
    from .._errors import POSE_COLUMNS

    k = POSE_COLUMNS.index(dof)
    a = amplitude if k < 3 else np.deg2rad(amplitude)
    p = np.zeros((points, 6))
    p[:, k] = a * np.sin(2 * np.pi * cycles * np.arange(points) / points)
    return p


PLANS = {"x_line": plan_x_line, "random": plan_random, "grid": plan_grid, "swing": plan_swing}

# --- the true table -------------------------------------------------------------------------


def perturb_table(
    table: Table, seed: int = 0, joint_sigma: float = 0.010, zero_sigma: float = 0.050
) -> Table:
    """A hardware realisation: joint centres (each coordinate) and L0 off by normal errors."""
    rng = np.random.default_rng(seed)
    return replace(
        table,
        base_joints=np.asarray(table.base_joints) + joint_sigma * rng.normal(size=(6, 3)),
        platform_joints=np.asarray(table.platform_joints) + joint_sigma * rng.normal(size=(6, 3)),
        zero_lengths=np.asarray(table.zero_lengths) + zero_sigma * rng.normal(size=6),
    )


def _reading(target, row):
    """One stop's full 6-D reading: `row` = (platform pose, instrument frame), (6,) each."""
    pose, frame = row
    return observe(pose, frame, target)


def simulate(
    nominal: Table,
    true: Table,
    poses,
    instrument: Instrument,
    *,
    effects=None,
    compensated: bool = True,
    compensate: bool | None = None,
    frame=(0, 0, 0, 0, 0, 0),
    target=(0, 0, 0, 0, 0, 0),
    session="1",
    temperature=None,
    payload=None,
    time=None,
    frame_drift=(0, 0, 0, 0, 0, 0),
    seed: int = 0,
) -> Measurements:
    """Measurements of the `true` table driven by a controller that believes `nominal`.

    The controller commands `actuator_command(nominal, poses, compensated)` (rows in the order
    the table visits them); the true table (with `effects`, default its own hardware effects:
    the spiral term) settles at the exact forward-kinematics pose in each stop's context
    (direction of travel from the row order, `temperature` °C and `payload` kg: scalars or
    (N,), `session`: one label or (N,) labels, `time` (N,) s: the clock the drift term `t`
    runs over, default the row order); the instrument (`target` (6,), `frame` (6,)
    or one row per session, mm / rad, drifting by `frame_drift` (6,) or one row per session
    from the file's time 0 to 1, `Context.time`) reads it with its noise. Returns the rows with
    commanded lengths, the instrument's columns and its σ (and temperature / payload if
    given).
    """
    poses = np.asarray(poses, dtype=float)
    n = len(poses)
    compensated = renamed_argument(compensated, compensate, "compensate", "compensated", "simulate")
    cmd = np.asarray(actuator_command(nominal, poses, compensated))
    labels = np.broadcast_to(np.asarray(session).astype(str), (n,))
    sess = np.unique(labels, return_index=True)
    order = [sess[0][k] for k in np.argsort(sess[1])]
    index = np.array([order.index(lab) for lab in labels])
    temp = None if temperature is None else np.broadcast_to(np.asarray(temperature, float), (n,))
    load = None if payload is None else np.broadcast_to(np.asarray(payload, float), (n,))
    ctx = Context(
        directions(cmd),
        20.0 if temp is None else temp,
        0.0 if load is None else load,
        index,
        run_time(n, time, index),
    )
    actual = forward(
        true, cmd, effects=effects, nominal=nominal, guess=poses, context=batch_context(n, ctx)
    )
    frames = np.broadcast_to(np.asarray(frame, float), (len(order), 6))
    drift = np.broadcast_to(np.asarray(frame_drift, float), (len(order), 6))
    seen = frames[index] + drift[index] * np.asarray(ctx.time)[:, None]
    target = device_array(target, dtype=np.float64)
    reading = np.asarray(run_batch(_reading, target, (np.asarray(actual), seen)))
    noise = np.nan_to_num(np.asarray(instrument.noise, float))
    reading = reading + noise * np.random.default_rng(seed).normal(size=reading.shape)
    mask = instrument.mask
    measured = np.where(mask, reading, np.nan)
    sigma = np.where(mask, np.asarray(instrument.noise, float), np.nan) * np.ones_like(measured)
    return Measurements(
        poses,
        measured,
        cmd,
        sigma,
        None if temp is None else np.array(temp),
        None if load is None else np.array(load),
        session=np.array(labels),
        time=None if time is None else np.array(time, float),
    )


def concat(*parts: Measurements) -> Measurements:
    """Rows of several measurement sets, in order (e.g. two sessions)."""

    def cat(name):
        vals = [getattr(p, name) for p in parts]
        return None if any(v is None for v in vals) else np.concatenate(vals)

    return Measurements(
        cat("cmd_pose"),
        cat("measured"),
        cat("cmd_lengths"),
        cat("sigma"),
        cat("temperature"),
        cat("payload"),
        cat("session"),
        time=cat("time"),
    )
