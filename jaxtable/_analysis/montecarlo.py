"""Monte Carlo propagation of a tolerance budget through the exact forward kinematics:
hardware realisations × poses, each solved by Newton with its effects inside."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from .._api import actuator_command
from .._batch import run_batch
from .._errors import check_finite_poses, require_x64
from .._forward import RESULTS, ForwardOptions, forward_one
from .._rotation import pose_error
from .._table import Table
from .tolerances import Tolerances, budget_effects, sample_hardware


def _mc_sample(shared, sample):
    """Pose errors (P, 6) and results (P,) of one hardware realisation `sample` = (table,
    effects) at the commanded poses; shared = (extensions s (P, 6), poses (P, 6), options)."""
    s, poses, options = shared
    t, e = sample

    def one_pose(si, p):
        q, result, _, _ = forward_one(t, e, si, p, options)
        return pose_error(q, p), result

    return jax.vmap(one_pose)(s, poses)


def monte_carlo(
    table: Table,
    tolerances: Tolerances | ArrayLike = Tolerances(),  # an array: the deprecated order
    poses: ArrayLike | Tolerances | None = None,
    n_samples: int = 1000,
    *,
    seed: int = 0,
    options: ForwardOptions = ForwardOptions(),
    allow_failures: bool = False,
):
    """Pose errors of `n_samples` hardware realisations of `tolerances` at commanded `poses`
    (P, 6) (argument order as `error_map`: model, tolerances, poses).

    The controller commands the nominal inverse kinematics with spiral compensation; each
    realisation (joints, L0, lead scale, spiral lead normal; clearance ±w/2, see
    `sample_hardware`) moves by the exact forward kinematics. Returns errors
    (n_samples, P, 6): translation mm, rotation vector rad.

    A realisation for which Newton finds no pose near the commanded one (near a singularity
    the assembly may not exist or may flip) raises RuntimeError, or with
    `allow_failures=True` gives NaN rows (count them with `np.isnan(err[..., 0])`).
    """
    if not isinstance(tolerances, Tolerances) and (poses is None or isinstance(poses, Tolerances)):
        warnings.warn(
            "monte_carlo(table, poses, tolerances) is deprecated: call "
            "monte_carlo(table, tolerances, poses), the order of error_map",
            DeprecationWarning,
            stacklevel=2,
        )
        tolerances, poses = (Tolerances() if poses is None else poses), tolerances
    if poses is None:
        raise ValueError("monte_carlo needs the commanded poses (P, 6)")
    require_x64()
    check_finite_poses(poses)
    poses = jnp.asarray(poses, dtype=jnp.float64).reshape(-1, 6)
    tables, effects = sample_hardware(table, tolerances, n_samples, jax.random.PRNGKey(seed))
    s = actuator_command(table, poses, effects=budget_effects(table), check=False)
    s = s - table.zero_lengths
    chunk = max(1, (1 << 16) // poses.shape[0])
    # a row is a forward solve of every pose: pad small sample counts to 8, not SMALL_BATCH
    err, result = run_batch(
        _mc_sample, (s, poses, options), (tables, effects), chunk=chunk, min_rows=8
    )
    ok = np.asarray(result == RESULTS.successful)
    err = np.asarray(err)
    if allow_failures:
        return np.where(ok[..., None], err, np.nan)
    if not ok.all():
        bad = np.argwhere(~ok)
        first = jax.tree.map(lambda v: v[tuple(bad[0])], result)
        raise RuntimeError(
            f"{len(bad)} of {ok.size} Monte Carlo solves failed (first: sample {bad[0][0]}, "
            f"pose {bad[0][1]}: {RESULTS[first]}); the tolerances may be too large for the "
            f"workspace"
        )
    return err
