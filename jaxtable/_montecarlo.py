"""Monte Carlo propagation of a tolerance budget through the exact forward kinematics:
hardware realisations × poses, each solved by Newton with its effects inside."""

import jax
import jax.numpy as jnp
import numpy as np

from ._api import actuator_command
from ._batch import run_batch
from ._errors import check_finite_poses, require_x64
from ._forward import ForwardOptions, forward_one
from ._rotation import rotation_matrix
from ._table import Table
from ._tolerance import Tolerances, budget_effects, sample_hardware


def rotation_error_vector(actual, commanded):
    """Rotation vector (rad, base frame) of R(actual) R(commanded)ᵀ, for (…, 3) Euler angles.
    Exact log map (angle from atan2 of the skew and symmetric parts)."""
    Ra = rotation_matrix(actual)
    Rc = rotation_matrix(commanded)
    D = Ra @ Rc.T
    w = 0.5 * jnp.array([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]])
    sin = jnp.linalg.norm(w)
    cos = 0.5 * (jnp.trace(D) - 1.0)
    theta = jnp.arctan2(sin, cos)
    scale = jnp.where(sin > 1e-12, theta / jnp.where(sin > 1e-12, sin, 1.0), 1.0 + sin**2 / 6)
    return w * scale


def _pose_error(q, pose):
    return jnp.concatenate([q[:3] - pose[:3], rotation_error_vector(q[3:], pose[3:])])


def _mc_sample(shared, sample):
    """Pose errors (P, 6) and codes (P,) of one hardware realisation `sample` = (table,
    effects) at the commanded poses; shared = (extensions s (P, 6), poses (P, 6), options)."""
    s, poses, options = shared
    t, e = sample

    def one_pose(si, p):
        q, code, _, _ = forward_one(t, e, si, p, options)
        return _pose_error(q, p), code

    return jax.vmap(one_pose)(s, poses)


def monte_carlo(
    table: Table,
    poses,
    tolerances: Tolerances = Tolerances(),
    n_samples: int = 1000,
    *,
    seed: int = 0,
    options: ForwardOptions = ForwardOptions(),
    allow_failures: bool = False,
):
    """Pose errors of `n_samples` hardware realisations at commanded `poses` (P, 6).

    The controller commands the nominal inverse kinematics with spiral compensation; each
    realisation (joints, L0, lead scale, spiral lead normal; clearance ±w/2, see
    `sample_hardware`) moves by the exact forward kinematics. Returns errors
    (n_samples, P, 6): translation mm, rotation vector rad.

    A realisation for which Newton finds no pose near the commanded one (near a singularity
    the assembly may not exist or may flip) raises RuntimeError, or with
    `allow_failures=True` gives NaN rows (count them with `np.isnan(err[..., 0])`).
    """
    require_x64()
    check_finite_poses(poses)
    poses = jnp.asarray(poses, dtype=jnp.float64).reshape(-1, 6)
    tables, effects = sample_hardware(table, tolerances, n_samples, jax.random.PRNGKey(seed))
    s = actuator_command(table, poses, effects=budget_effects(table), check=False)
    s = s - table.zero_lengths
    chunk = max(1, (1 << 16) // poses.shape[0])
    err, code = run_batch(_mc_sample, (s, poses, options), (tables, effects), chunk=chunk)
    code = np.asarray(code)
    err = np.asarray(err)
    if allow_failures:
        return np.where((code == 0)[..., None], err, np.nan)
    if np.any(code != 0):
        bad = np.argwhere(code != 0)
        raise RuntimeError(
            f"{len(bad)} of {code.size} Monte Carlo solves failed (first: sample {bad[0][0]}, "
            f"pose {bad[0][1]}, code {code[tuple(bad[0])]}); the tolerances may be too large "
            f"for the workspace"
        )
    return err
