"""Error types raised at the public boundary, and the input checks that raise them."""

import os
import warnings

import jax
import numpy as np

POSE_COLUMNS = ("x", "y", "z", "roll", "pitch", "yaw")


class TableFileError(ValueError):
    """A table file (TOML) is missing a key, has a value of the wrong shape, or describes a
    geometry that cannot work (zero or non-unit joint axis, axis parallel to its leg)."""


class KinematicsError(ValueError):
    """A pose or command is invalid (non-finite, outside the stroke) or a solve failed."""


def env_switch(name: str, off: str, on: str) -> bool:
    """Whether the environment variable `name` (0 or 1, default 1) is on; any other value
    raises ValueError naming the variable and what 0 (`off`) and 1 (`on`) mean."""
    raw = os.environ.get(name, "1").strip()
    if raw not in ("0", "1"):
        raise ValueError(f"${name} must be 0 ({off}) or 1 ({on}), got {raw!r}")
    return raw == "1"


def require_x64() -> None:
    if not jax.config.jax_enable_x64:
        raise RuntimeError(
            "jaxtable computes in float64 (micrometres on metre-scale legs), but "
            "jax_enable_x64 is off. `import jaxtable` switches it on; something switched it "
            "off again. Call jax.config.update('jax_enable_x64', True)."
        )


def is_concrete(*xs) -> bool:
    """True if no argument (or pytree leaf) is a JAX tracer, so values can be inspected."""
    leaves = jax.tree_util.tree_leaves(xs)
    return not any(isinstance(x, jax.core.Tracer) for x in leaves)


def _index_str(flat_index: int, batch_shape: tuple[int, ...]) -> str:
    if len(batch_shape) == 0:
        return "the pose"
    idx = np.unravel_index(flat_index, batch_shape)
    return "pose [" + ", ".join(str(int(i)) for i in idx) + "]"


def describe_rows(bad: np.ndarray, batch_shape: tuple[int, ...], what, limit: int = 5) -> str:
    """Describe the first `limit` flagged rows. `bad`: bool, flat (N,). `what(i)` -> reason."""
    rows = np.flatnonzero(bad)
    lines = [f"  {_index_str(int(i), batch_shape)}: {what(int(i))}" for i in rows[:limit]]
    if len(rows) > limit:
        lines.append(f"  ... and {len(rows) - limit} more")
    return "\n".join(lines)


def check_finite_poses(poses, name: str = "poses") -> None:
    """Raise KinematicsError naming the first non-finite pose entries. `poses`: (..., 6)."""
    if not is_concrete(poses):
        return
    p = np.asarray(poses)
    if p.shape[-1:] != (6,):
        raise KinematicsError(
            f"{name} must have shape (..., 6) = (x, y, z, roll, pitch, yaw); got {p.shape}"
        )
    flat = p.reshape(-1, 6)
    bad = ~np.isfinite(flat)
    if bad.any():
        rows = bad.any(axis=1)

        def what(i):
            cols = [POSE_COLUMNS[c] for c in np.flatnonzero(bad[i])]
            return f"non-finite {', '.join(cols)} ({flat[i].tolist()})"

        raise KinematicsError(
            f"{name} has non-finite values:\n" + describe_rows(rows, p.shape[:-1], what)
        )


def check_finite_lengths(lengths, name: str = "commands") -> None:
    """Raise KinematicsError naming non-finite leg lengths. `lengths`: (..., 6)."""
    if not is_concrete(lengths):
        return
    v = np.asarray(lengths)
    if v.shape[-1:] != (6,):
        raise KinematicsError(f"{name} must have shape (..., 6), one value per leg; got {v.shape}")
    flat = v.reshape(-1, 6)
    bad = ~np.isfinite(flat)
    if bad.any():

        def what(i):
            legs = [str(c + 1) for c in np.flatnonzero(bad[i])]
            return f"non-finite length on leg {', '.join(legs)}"

        raise KinematicsError(
            f"{name} has non-finite values:\n" + describe_rows(bad.any(1), v.shape[:-1], what)
        )


def renamed_argument(new, old, old_name: str, new_name: str, where: str):
    """Value of a keyword argument renamed from `old_name` to `new_name`: the old keyword
    (not None) wins, with a DeprecationWarning; it is kept for one release."""
    if old is None:
        return new
    warnings.warn(
        f"{where}: the keyword `{old_name}` is deprecated, use `{new_name}`",
        DeprecationWarning,
        stacklevel=3,
    )
    return old
