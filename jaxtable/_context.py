"""The recording context of one stop: what an effect may depend on besides pose and s."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float, Int

from ._errors import is_concrete
from ._jit import LARGE_BATCH, device_array

REFERENCE_TEMPERATURE = 20.0  # °C


class Context(eqx.Module):
    """Context of ONE stop (batched: every leaf gets a leading axis).

    - `direction` (6,): +1 if leg i last moved out (extending), −1 if in (backlash);
    - `temperature` (): °C (thermal; default 20 °C, the reference);
    - `payload` (): kg on the platform besides its own mass (compliance; at the platform CoG);
    - `session` (): int, index of the recording session in order of first appearance
      (rehoming; 0 = the first);
    - `time` (): when the stop was measured, scaled to 0..1 over the file (`run_time`: the
      file's `time` column where it has one, else row index / (rows − 1); the discovery
      dictionary's drift term `t`; default 0).
    """

    direction: Float[ArrayLike, "6"]
    temperature: Float[ArrayLike, ""]
    payload: Float[ArrayLike, ""]
    session: Int[ArrayLike, ""]
    time: Float[ArrayLike, ""]

    def __init__(
        self, direction=1.0, temperature=REFERENCE_TEMPERATURE, payload=0.0, session=0, time=0.0
    ):
        # numpy where concrete (`_jit.device_array`): eagerly, each conversion or broadcast
        # compiled a program of its own
        xp = np if is_concrete(direction) else jnp
        direction = xp.asarray(direction, dtype=np.float64)
        if direction.ndim == 0:
            direction = xp.broadcast_to(direction, (6,))
        self.direction = device_array(direction)
        self.temperature = device_array(temperature, dtype=np.float64)
        self.payload = device_array(payload, dtype=np.float64)
        self.session = device_array(session, dtype=np.int32)
        self.time = device_array(time, dtype=np.float64)


def batch_context(n: int, context: "Context | None" = None) -> Context:
    """A Context with leading axis n on every leaf: `context` broadcast (None = the home
    context); a leaf may be shared (no batch axis) or per stop (leading axis n)."""
    c = Context() if context is None else context
    direction = jnp.asarray(c.direction)
    if direction.shape[:-1] not in ((), (n,)):
        raise ValueError(
            f"context direction has shape {direction.shape}, expected (6,) or ({n}, 6)"
        )
    for name in ("temperature", "payload", "session", "time"):
        if jnp.shape(getattr(c, name)) not in ((), (n,)):
            raise ValueError(
                f"context {name} has shape {jnp.shape(getattr(c, name))}, expected () or ({n},)"
            )
    # numpy where nothing is traced: an eager jnp.broadcast_to compiles a program per shape
    xp = np if all(is_concrete(x) for x in jax.tree.leaves(c)) else jnp
    return Context(
        xp.broadcast_to(xp.asarray(c.direction), (n, 6)),
        xp.broadcast_to(xp.asarray(c.temperature), (n,)),
        xp.broadcast_to(xp.asarray(c.payload), (n,)),
        xp.broadcast_to(xp.asarray(c.session), (n,)),
        xp.broadcast_to(xp.asarray(c.time), (n,)),
    )


def run_time(n: int, time=None, session=None) -> np.ndarray:
    """(n,) the stops' time over a file of n rows, scaled to 0..1: from the clock `time` (N,)
    (s; NaN where not logged: interpolated by row) where it has two different readings, so
    that a pause between stops is a pause in the drift; else row index / (n − 1).

    `session` (N,) labels or indices: a clock may start again where the session changes
    (each recording run logged on its own clock, `time_goes_back`); the runs are then put
    end to end in row order, each begun one typical step (the median step between the
    readings of a run) after the last reading before it, since the pause between them is
    not in the file. Raises ValueError naming the row where the clock goes back within a
    session (rows are in the order the table moved)."""
    rows = np.arange(n, dtype=float)
    t = None if time is None else np.asarray(time, float)
    ok = np.zeros(n, bool) if t is None else np.isfinite(t)
    back = None if t is None else time_goes_back(t, session)
    if back is not None:
        before = t[:back][ok[:back]][-1]
        raise ValueError(
            f"row {back + 1}, column 'time': the clock goes back ({before:g} before it, "
            f"{t[back]:g} here); rows are in the order the table moved"
        )
    if ok.sum() < 2:
        return rows / max(n - 1, 1)
    step = np.diff(t[ok])
    if np.any(step < 0):  # runs on their own clocks: put end to end
        forward = step[step >= 0]
        typical = np.median(forward[forward > 0]) if np.any(forward > 0) else 1.0
        t = t.copy()
        t[ok] = t[ok][0] + np.concatenate([[0.0], np.cumsum(np.where(step < 0, typical, step))])
    if t[ok][-1] == t[ok][0]:
        return rows / max(n - 1, 1)
    t = np.interp(rows, rows[ok], t[ok])
    return (t - t[0]) / (t[-1] - t[0])


def clock_restarts(time) -> int:
    """How many times the clock `time` (N,) goes back (NaN cells skipped): where
    `time_goes_back` found nothing, the times it starts again with a new session."""
    t = np.asarray(time, float)
    ok = np.flatnonzero(np.isfinite(t))
    return int(np.sum(np.diff(t[ok]) < 0))


def time_goes_back(time, session=None) -> int | None:
    """The first row (0-based) whose clock reading is earlier than the one logged before it
    (NaN cells skipped) while the session is the same (`session` (N,) labels or indices;
    None: one session), or None. A clock that starts again with a new session is a
    recording run logged on its own clock."""
    t = np.asarray(time, float)
    ok = np.flatnonzero(np.isfinite(t))
    drop = np.diff(t[ok]) < 0
    if session is not None:
        s = np.asarray(session)
        # a session change anywhere between two logged readings
        changes = np.concatenate([[0], np.cumsum(s[1:] != s[:-1])])
        drop &= changes[ok[1:]] == changes[ok[:-1]]
    drop = np.flatnonzero(drop)
    return None if len(drop) == 0 else int(ok[drop[0] + 1])


def directions(cmd_lengths: np.ndarray) -> np.ndarray:
    """(N, 6) ±1 from the row order of commanded lengths (N, 6): +1 if the leg last moved
    out, −1 if in; the first row +1 and a leg that did not move keeps its sign."""
    d = np.sign(np.diff(np.asarray(cmd_lengths), axis=0))
    d = np.concatenate([np.ones((1, 6)), d])
    rows = np.arange(len(d))[:, None]
    last = np.maximum.accumulate(np.where(d != 0, rows, 0), axis=0)
    return np.take_along_axis(d, last, axis=0)


def split_context(n: int, context: "Context | None" = None):
    """(shared, per_row) for a batch of n stops. Exactly one of the two is None.

    From `LARGE_BATCH` rows, the context itself when no leaf has a batch axis (shared by
    every row, never broadcast to n copies). Otherwise, and always for a smaller batch,
    `batch_context(n, context)`: a small batch's kernel then compiles once, whatever the
    kind of its context."""
    c = Context() if context is None else context
    if (
        n >= LARGE_BATCH
        and jnp.ndim(c.direction) == 1
        and all(jnp.ndim(getattr(c, k)) == 0 for k in ("temperature", "payload", "session", "time"))
    ):
        return c, None
    return None, batch_context(n, c)
