"""Calibration: fit the free parameters of the model to measured data (optimistix
Gauss-Newton with SVD steps, or Levenberg-Marquardt, through the exact forward kinematics),
with the instrument's frame and target as nuisance parameters, an explicit gauge, covariance
and an identifiability report.

Residual of row r, column c (measured only): (reading_c(q_r) − measured_rc) / σ_rc, where q_r
is the forward-kinematics pose of the fitted table for the row's commanded lengths (converted
to actuator extensions with the controller's nominal L0) and the reading is the instrument's
view of it (`_instrument.observe`) in the frame of the row's session.

Gauge. An instrument frame estimated with 6 DOF can absorb any rigid motion of the base
joints, and a target offset any rigid motion of the platform joints (to first order): those
directions are removed from the joint parameters (`gauge` in the result says which), so the
joints are fitted modulo rigid motions and the frame/target carry the rest.
"""

import dataclasses
import functools
import warnings
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree

from .. import _params as params
from .._analysis.tolerances import Tolerances
from .._api import actuator_command
from .._batch import _in_pieces, _pad_rows, _pool, _slice_rows, cpu_workers
from .._context import Context, directions, run_time
from .._effects import resolve_effects
from .._errors import POSE_COLUMNS, KinematicsError, TableFileError, is_concrete
from .._forward import RESULTS, ForwardOptions, forward_one
from .._jit import device_array, jit
from .._kinematics import in_stroke
from .._rotation import (
    best_rotation,
    euler_from_matrix,
    wrap_reading_difference,
)
from .._table import Table, check_table, replace
from .._threads import one_blas_thread
from .aliases import instrument_scale
from .instruments import observe
from .measurements import (
    Measurements,
    check_alignment,
    check_angle_convention,
    check_commanded,
    check_units,
    nominal_lengths,
    require_measured,
)
from .noise import (
    NoiseEstimate,
    NoiseModel,
    column_groups,
    equal_sigma_ps,
    group_scales,
    noise_model,
    pool_columns,
    pooled_scales,
    robust_scales,
    screen_groups,
)
from .noise import estimate as noise_estimate
from .outliers import ALPHA, TRIAL_ROUNDS, GrossError, prescreen, repeat_words, without
from .outliers import screen as screen_gross_errors
from .prior import check as prior_check
from .prior import weights as prior_weights
from .stops import merge_stops, weigh_stops

JOINTS = params.JOINTS
COLUMNS = ("x", "y", "z", "roll", "pitch", "yaw")
METHODS = ("gauss_newton", "levenberg_marquardt")


def rigid_motion_basis(points: np.ndarray) -> np.ndarray:
    """(18, 6) orthonormal basis of the first-order rigid motions of 6 points (6, 3)."""
    cols = []
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1.0
        cols.append(np.tile(e, 6))
        cols.append(np.cross(e, points).reshape(-1))
    q, _ = np.linalg.qr(np.stack(cols, 1))
    return q


def complement_basis(points: np.ndarray) -> np.ndarray:
    """(18, 12) orthonormal basis of joint displacements that are not rigid motions."""
    G = rigid_motion_basis(points)
    u, _, _ = np.linalg.svd(G, full_matrices=True)
    return u[:, 6:]


@dataclass(frozen=True)
class Layout:
    """Static description of the fitted parameters: which leaves, the gauge bases, which
    frame/target components are estimated."""

    free: tuple
    frame_dofs: tuple
    target_dofs: tuple
    n_sessions: int
    gauge: tuple  # names of the joint sets fitted modulo rigid motions
    # the instrument frame drifts linearly over the file's time (θ "frame_drift": per session,
    # the frame DOFs' change from time 0 to 1, `Context.time`): a tracker or its stand
    # warming up
    frame_drift: bool = False


def nuisance_dofs(measured_mask: np.ndarray, motion=None) -> tuple[tuple, tuple]:
    """(frame DOFs, target DOFs) an instrument that reads the columns `measured_mask` (6,)
    can see (indices into x, y, z, roll, pitch, yaw), on a run whose commanded positions
    span `motion` (3,) mm (default: every axis moves).

    Frame: a translation along axis k shows in position column k only. A rotation about
    axis a shows in angle column a, and to first order in a position column b ≠ a through
    the motion along the third axis c (an interferometer beam tilted about z reads y motion
    in x): it is estimated when angle a is measured, or some position column b ≠ a is and the
    run moves more than 1 mm along the matching c. (On a line along x the tilts enter only at
    second order, as a scale of x that the geometry's scale already carries: estimating them
    would let the fit wander.) The target offset on the platform: its position when all
    three positions are read (a point tracker follows a point), its orientation when all
    three angles are. The fit's identifiability report says what a plan still leaves
    undetermined.
    """
    m = np.asarray(measured_mask, bool)
    moves = np.ones(3, bool) if motion is None else np.asarray(motion, float) > 1.0
    frame = [k for k in range(3) if m[k]]
    for a in range(3):
        cross = any(m[b] and moves[3 - a - b] for b in range(3) if b != a)
        if m[3 + a] or cross:
            frame.append(3 + a)
    target = ([0, 1, 2] if m[:3].all() else []) + ([3, 4, 5] if m[3:].all() else [])
    return tuple(frame), tuple(target)


class Problem(eqx.Module):
    """Arrays of one calibration problem (the jitted fit takes it as an argument, so data
    sets of the same shape reuse one compilation)."""

    nominal: Table
    start: Table
    effects: dict
    s: jax.Array  # (N, 6) actuator extensions
    guess: jax.Array  # (N, 6) commanded poses
    measured: jax.Array  # (N, 6) NaN -> 0
    weight: jax.Array  # (N, 6) 1/σ, 0 where not measured
    session: jax.Array  # (N,) int
    bases: dict  # joint set -> (18, k) basis
    ctx: Context  # batched (N,) context of every stop


def build_model(problem: Problem, layout: Layout, theta):
    """(table, effects, frame (S, 6), target (6,), frame drift (S, 6)) of θ: the start
    table and effects moved by θ's steps, the instrument frame of each session and its
    drift over the file's time (zeros unless `layout.frame_drift`)."""
    table, effects = problem.start, problem.effects
    # in numpy where nothing is traced (the fitted model a fit reports): eagerly, each jnp
    # operation below compiled a program of its own
    concrete = is_concrete(table, effects, theta, problem.bases)
    xp = np if concrete else jnp
    changes = {}
    for name in layout.free:
        step = xp.asarray(theta[name])
        if name in params.JOINTS:
            step = (xp.asarray(problem.bases[name]) @ step).reshape(6, 3)
        leaf = params.leaf(name)  # a shared parameter's scalar step moves every leg's value
        start = changes[leaf] if leaf in changes else xp.asarray(params.get(table, effects, leaf))
        changes[leaf] = start + step
    if concrete:
        changes = {k: device_array(v) for k, v in changes.items()}
    table, effects = params.replace(table, effects, changes)
    frame = _placed(xp, (layout.n_sessions, 6), layout.frame_dofs, theta.get("frame"))
    target = _placed(xp, (6,), layout.target_dofs, theta.get("target"))
    drift = _placed(
        xp,
        (layout.n_sessions, 6),
        layout.frame_dofs if layout.frame_drift else (),
        theta.get("frame_drift"),
    )
    if concrete:
        frame, target, drift = (device_array(x) for x in (frame, target, drift))
    return table, effects, frame, target, drift


def _placed(xp, shape: tuple, dofs: tuple, values):
    """Zeros of `shape` with `values` in the columns `dofs` of the last axis (zeros alone
    where there are no `dofs`), with `xp` = numpy or jax.numpy."""
    if not dofs:
        return xp.zeros(shape)
    if xp is np:
        out = np.zeros(shape)
        out[..., list(dofs)] = np.asarray(values)
        return out
    return jnp.zeros(shape).at[..., np.array(dofs)].set(values)


def _rows(problem: Problem):
    """The per-row arrays of `problem`, in the argument order of `_row_residual`."""
    return (
        problem.s,
        problem.guess,
        problem.session,
        problem.ctx,
        problem.measured,
        problem.weight,
    )


FIT_BLOCK = 64
"""Stops in each compiled block of a fit's residual and Jacobian (`jacobian_in_chunks`):
fits of any number of stops share one compiled program per model structure. Measured on
the 164-parameter Jacobian of a diagnosis: 38 µs a stop in blocks of 64, 41–44 in blocks
of 96 or 128, 52 in blocks of 32 and 111 in blocks of 16 (a call costs ~1.2 ms however
small). The last block is padded: a 150-stop fit evaluates 192 stops, a 14-stop fit 64."""


@dataclass(frozen=True)
class _Canonical:
    """The block programs' view of a fit's parameters (`_canonical`): every fit of one model
    structure (effects present, sessions up to a power of two, other table leaves freed)
    runs one compiled block program, whatever it frees, which instrument columns it reads
    (frame and target DOFs) and whether its joint sets are gauged.

    `layout`: the canonical layout: the geometry (and any other freed table leaf), every
    field of every effect in the model per element, all six frame DOFs of every session
    and of the target, no gauge (joint steps in plain coordinates); frames and per-session
    effect rows for `canonical_sessions` sessions (a power of two, at least 2). `template`:
    the canonical θ at zero (its ravel order is the programs'). `embed` (P_c, P): f_c =
    embed @ f maps a fit's flat parameters f (laid out as its θ) onto the canonical ones;
    `build_model` is linear in θ, so the model is the same, and the fit's Jacobian is
    J_c @ embed: a gauged joint set's columns are its basis, a shared field's
    (`thermal.alpha[all]`) ones on every leg's element, a frame or target DOF the one it
    sets."""

    layout: Layout
    template: dict
    embed: np.ndarray
    # (P,) the row of embed of each column that is one canonical column (a selection), 0
    # for the others; per other block of θ: (first, last + 1 column, first, last + 1 row
    # of embed)
    pick: np.ndarray
    products: tuple = ()

    def jacobian(self, J_c: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """J_c @ embed (M, P) for the canonical Jacobian J_c (M, P_c), written into `out`
        (M, P, C-contiguous) where given: the columns that are one canonical column each in
        one gather over J_c's rows (`pick`), then each other block of θ as a product over
        the rows of `embed` it reaches (`products`). The dense product spent ~3 ms of each
        Jacobian of a 150-stop diagnosis multiplying zeros; a copy or product per block of θ
        passed over J_c once a block (28 blocks in a diagnosis: 32 → 16 ms a Jacobian of
        5,000 stops and 204 canonical columns)."""
        # the products' columns are overwritten; "clip": `out` written directly (the default
        # mode buffers it), and every index of `pick` is in range anyway
        out = np.take(J_c, self.pick, axis=1, out=out, mode="clip")
        for j0, j1, r0, r1 in self.products:  # blocks of parameters, not data
            out[:, j0:j1] = J_c[:, r0:r1] @ self.embed[r0:r1, j0:j1]
        return out

    def unravel(self, flat) -> dict:
        """The canonical θ (a dict of numpy arrays) of the flat canonical parameters `flat`,
        sliced in numpy (an eager `ravel_pytree` unravel compiles a slice per shape)."""
        return _unflat(self.template, flat)


def _canonical(problem: Problem, layout: Layout, theta) -> _Canonical:
    """The canonical parameters of a fit laid out as `layout` and `theta` (see `_Canonical`),
    kept for the fit's later steps (a fit asks at every evaluation)."""
    bases = tuple(np.asarray(problem.bases[n]) for n in JOINTS)
    key = (
        layout,
        tuple((k, np.shape(v)) for k, v in sorted(theta.items())),
        tuple(
            (e, jax.tree.structure(v), tuple(np.shape(x) for x in jax.tree.leaves(v)))
            for e, v in sorted(problem.effects.items())
        ),
        tuple((b.shape, b.tobytes()) for b in bases),
    )
    found = _CANONICAL.get(key)
    if found is None:
        found = _CANONICAL[key] = _make_canonical(problem, layout, theta)
        while len(_CANONICAL) > 64:
            _CANONICAL.pop(next(iter(_CANONICAL)))
    return found


_CANONICAL: dict = {}


def _flat(theta: dict) -> np.ndarray:
    """`ravel_pytree(theta)[0]` in numpy for θ, a dict of arrays (keys sorted, each raveled in
    C order): eager JAX reshaped and concatenated leaf by leaf, ~4 ms a fit."""
    return np.concatenate([np.ravel(np.asarray(theta[k], float)) for k in sorted(theta)])


def _unflat(theta: dict, flat) -> dict:
    """θ laid out as `theta` (a dict of arrays) from the flat parameters `flat`, as numpy
    arrays: the inverse of `_flat` (`ravel_pytree`'s unravel, without its eager slices).
    Host arrays: a fit's θ goes to numpy (`build_model`'s concrete path) or as an argument
    to a compiled program, where a copy to the device first (~30 µs an array) was a
    fitted θ's largest host cost after its Jacobians (~2 % of the default suite)."""
    flat, out, at = np.asarray(flat, float), {}, 0
    for key in sorted(theta):
        shape = np.shape(theta[key])
        n = int(np.prod(shape))
        out[key] = flat[at : at + n].reshape(shape).copy()
        at += n
    return out


def _make_canonical(problem: Problem, layout: Layout, theta) -> _Canonical:
    extra = tuple(n for n in params.TABLE_LEAVES if n in layout.free and n not in params.GEOMETRY)
    fields = tuple(
        f"{e}.{f}" for e in sorted(problem.effects) for f in type(problem.effects[e]).fields
    )
    sessions = canonical_sessions(layout.n_sessions)
    effects = _padded_effects(problem.effects, layout.n_sessions)
    lay = Layout(
        params.GEOMETRY + extra + fields, tuple(range(6)), tuple(range(6)), sessions, (), True
    )
    template = {  # a joint set's step in plain coordinates (18,), as `build_model` takes it
        n: np.zeros(18 if n in JOINTS else np.shape(params.get(problem.start, effects, n)))
        for n in lay.free
    }
    template["frame"] = np.zeros((sessions, 6))
    template["frame_drift"] = np.zeros((sessions, 6))
    template["target"] = np.zeros(6)
    start, at = {}, 0
    for key in sorted(template):  # `ravel_pytree` order: dict keys sorted
        start[key] = at
        at += template[key].size
    sizes = {k: int(np.asarray(v).size) for k, v in theta.items()}
    embed = np.zeros((at, sum(sizes.values())))
    j, pick, products = 0, np.zeros(embed.shape[1], dtype=np.intp), []
    for key in sorted(theta):  # blocks of parameters, not data
        n, c = sizes[key], start.get(params.leaf(key), 0)
        if key in params.JOINTS:
            embed[c : c + 18, j : j + n] = np.asarray(problem.bases[key])
        elif key in ("frame", "frame_drift", "target"):
            dofs = layout.target_dofs if key == "target" else layout.frame_dofs
            rows = np.add.outer(6 * np.arange(n // max(len(dofs), 1)), dofs).reshape(-1)
            embed[c + rows, j + np.arange(n)] = 1.0
        elif params.is_shared(key):
            embed[c : c + template[params.leaf(key)].size, j] = 1.0
        else:
            embed[c : c + n, j : j + n] = np.eye(n)
        block = embed[:, j : j + n]
        rows = np.flatnonzero(np.any(block != 0, axis=1))
        one = (np.sum(block != 0, axis=0) == 1) & (np.sum(block, axis=0) == 1)
        if one.all():  # each column one canonical column: gathered
            pick[j : j + n] = np.argmax(block != 0, axis=0)
        else:  # a product over the rows it reaches (none: columns of zeros)
            r0, r1 = (int(rows[0]), int(rows[-1]) + 1) if rows.size else (0, 0)
            products.append((j, j + n, r0, r1))
        j += n
    return _Canonical(lay, jax.tree.map(device_array, template), embed, pick, tuple(products))


_PLAIN_BASES = {n: np.eye(18) for n in JOINTS}


def canonical_sessions(n_sessions: int) -> int:
    """Sessions the block programs hold frames (and per-session effect rows) for: a power
    of two, at least 2, so that files of one and two sessions, and a file whose session a
    step in time split in two, share the program (rows no stop reads add nothing)."""
    return max(2, 1 << (n_sessions - 1).bit_length())


def _padded_effects(effects: dict, n_sessions: int) -> dict:
    """`effects` with their per-session fields (one row per later session: `rehoming`'s
    offsets, the discovered `session*s` terms; the fields whose shape `null` sets by the
    number of sessions) padded with zero rows to `canonical_sessions(n_sessions)`. The
    effects read the row of a stop's session, so rows beyond the data's sessions are never
    read."""
    out = {}
    for name, e in effects.items():
        sizes = _session_rows(type(e), n_sessions)
        grow = [f for f, (have, _) in sizes.items() if np.shape(getattr(e, f)) == have]
        if grow:
            padded = []
            for f in grow:
                v = np.asarray(getattr(e, f))
                extra = sizes[f][1][0] - v.shape[0]
                padded.append(device_array(np.concatenate([v, np.zeros((extra,) + v.shape[1:])])))
            e = eqx.tree_at(lambda m: [getattr(m, f) for f in grow], e, padded)
        out[name] = e
    return out


@functools.cache
def _session_rows(cls, n_sessions: int) -> dict:
    """{field: (shape for `n_sessions`, shape for `canonical_sessions`)} of the fields of
    effect class `cls` whose shape `null` sets by the number of sessions ({} for an effect
    without a per-session `null`)."""
    try:
        have, want = cls.null(n_sessions), cls.null(canonical_sessions(n_sessions))
    except Exception:
        return {}
    shapes = {f: (np.shape(getattr(have, f)), np.shape(getattr(want, f))) for f in cls.fields}
    return {f: pair for f, pair in shapes.items() if pair[0] != pair[1]}


def _stop_blocks(problem: Problem, layout: Layout, rows: int = FIT_BLOCK) -> list:
    """`problem` cut into blocks of `rows` stops for the block programs: [(block problem,
    stops used)], the last block padded by repeating its last stop with zero weight (so it
    adds nothing to a sum over rows), the joint bases plain and the per-session effect rows
    padded (the programs take canonical parameters, `_canonical`). The per-stop arrays are
    sliced in numpy (indexing jax arrays eagerly compiles a gather for every shape), and the
    blocks made by `dataclasses.replace` (`eqx.tree_at` flattens the whole problem for each:
    ~2.4 ms a block, a tenth of a warm 150-stop fit)."""
    n = problem.s.shape[0]
    per_stop = jax.tree.map(np.asarray, _rows(problem))
    plain = dataclasses.replace(
        problem,
        bases=jax.tree.map(device_array, _PLAIN_BASES),
        effects=_padded_effects(problem.effects, layout.n_sessions),
    )
    blocks = []
    for start in range(0, n, rows):  # blocks of a batch, not a loop over poses
        k = min(rows, n - start)
        chunk = list(_pad_rows(_slice_rows(per_stop, start, start + rows), rows))
        chunk[5] = np.where(np.arange(rows)[:, None] < k, chunk[5], 0.0)  # the weight
        s, guess, session, ctx, measured, weight = jax.tree.map(device_array, tuple(chunk))
        block = dataclasses.replace(
            plain, s=s, guess=guess, session=session, ctx=ctx, measured=measured, weight=weight
        )
        blocks.append((block, k))
    return blocks


def _row_residual(model, s, guess, session, ctx, measured, weight):
    """One data row: ((reading − measured) / σ (6,), 0 where not measured; whether the
    forward solve succeeded), for `model` = `build_model(...)`."""
    table, effects, frame, target, drift = model
    q, result, _, _ = forward_one(table, effects, s, guess, ForwardOptions(), ctx)
    seen = frame[session] + drift[session] * ctx.time
    diff = wrap_reading_difference(observe(q, seen, target) - measured)
    return diff * weight, result == RESULTS.successful


def _weighted_residual(problem: Problem, layout: Layout, theta):
    """(residual (N·6,), solved (N,)): (reading − measured) / σ per cell (0 where not
    measured), and whether each row's forward solve succeeded."""
    model = build_model(problem, layout, theta)
    r, solved = jax.vmap(lambda row: _row_residual(model, *row))(_rows(problem))
    return r.reshape(-1), solved


def residual(theta, args):
    problem, layout = args
    return _weighted_residual(problem, layout, theta)[0]


residual_jit = jit(residual)


def weighted_residual(problem: Problem, layout: Layout, theta) -> np.ndarray:
    """(reading − measured) / σ per cell (N, 6) at θ, 0 where not measured: `residual_jit`
    in blocks of `FIT_BLOCK` stops on the canonical parameters (`_canonical`: one compiled
    program per model structure, whatever the number of stops and the parameters freed)."""
    can = _canonical(problem, layout, theta)
    theta_c = can.unravel(can.embed @ _flat(theta))
    blocks = _stop_blocks(problem, layout)
    parts = _in_blocks(blocks, lambda b: residual_jit(theta_c, (b, can.layout)))
    return _joined(parts, blocks, 6).reshape(-1, 6)


def _residual_and_jacobian(problem, layout, unravel):
    """f ↦ (J (N·6, P), (residual (N·6,), solved (N,))) on the flat parameters: the weighted
    residual and its Jacobian, with whether each row's forward solve succeeded.

    Reverse mode row by row (`vmap` over rows of `jacrev`; the forward kinematics
    differentiate implicitly): a row's 6 residuals depend on all P parameters, so one row
    costs 6 backward passes where forward mode pushes P tangents (P = 54 for a geometric
    fit, 164 in the bundled example's diagnosis: 10 ms per Jacobian there instead of 62)."""

    def row(f, data):
        r, solved = _row_residual(build_model(problem, layout, unravel(f)), *data)
        return r, (r, solved)

    jac_rows = jax.vmap(jax.jacrev(row, has_aux=True), in_axes=(None, 0))

    def evaluate(f):
        J, (r, solved) = jac_rows(f, _rows(problem))
        return J.reshape(-1, f.shape[0]), (r.reshape(-1), solved)

    return evaluate


@jit
def _block_jacobian(problem: Problem, layout: Layout, theta0, f):
    """One block of stops at the flat parameters `f` (P,) (laid out as `theta0`): (J (B·6, P),
    r (B·6,), solved (B,)) of the weighted residual (`_residual_and_jacobian`)."""
    _, unravel = ravel_pytree(theta0)
    J, (r, solved) = _residual_and_jacobian(problem, layout, unravel)(f)
    return J, r, solved


def jacobian_in_chunks(
    problem: Problem, layout: Layout, theta, rows: int = FIT_BLOCK, *, flat=None, blocks=None
):
    """(J (N·6, P), residual (N·6,), solved (N,)) at θ, numpy: the weighted residual's
    Jacobian on the flat parameters (`_residual_and_jacobian`), evaluated in blocks of
    `rows` stops with the fit's block program (`_block_jacobian`) on the canonical
    parameters (`_canonical`), then J = J_c @ embed: one compiled program per model
    structure, whatever the number of stops and whatever the fit frees, the instrument reads
    or the gauge: a file of a new length, a fit of another parameter set or instrument,
    pose selection and the discrimination plan (whose candidate poses change in number from
    call to call) share it. `flat` (P,): the parameters as a flat vector laid out as `theta`
    (default θ itself); `blocks`: `_stop_blocks(problem, layout, rows)` when the caller has them
    (a fit evaluates each step on the same blocks).

    The blocks' programs are all started before any result is read, and each block's rows
    are embedded (`_Canonical.jacobian`) into J as soon as its program is through, while
    the next blocks compute: joining the blocks' J_c and embedding the whole afterwards
    passed twice over J_c (~26 ms an evaluation of 5,000 stops and 204 canonical
    columns, after the blocks' ~140 ms)."""
    flat = _flat(theta) if flat is None else np.asarray(flat)
    can = _canonical(problem, layout, theta)
    flat_c = can.embed @ flat  # host array: a copy to the device costs more than a few calls
    blocks = _stop_blocks(problem, layout, rows) if blocks is None else blocks
    out = _in_blocks(blocks, lambda b: _block_jacobian(b, can.layout, can.template, flat_c))
    J = np.empty((6 * sum(k for _, k in blocks), can.embed.shape[1]))
    start = 0
    for (J_b, _, _), (_, k) in zip(out, blocks):  # blocks of a batch, in order
        can.jacobian(np.asarray(J_b)[: 6 * k], out=J[6 * start : 6 * (start + k)])
        start += k
    r, solved = (_joined([o[i] for o in out], blocks, m) for i, m in ((1, 6), (2, 1)))
    return J, r, solved


POOL_BLOCKS = 8
"""From this many blocks a fit's blocks run from a pool of host threads, one per core
(`_in_blocks`)."""


def _in_blocks(blocks: list, call) -> list:
    """[call(block) for each block of `_stop_blocks`]; from `POOL_BLOCKS` blocks on, on
    every core from a pool of host threads (XLA runs programs called from different threads
    at once; `_batch`). XLA already spreads one block's program over the cores in part:
    the fit of 10,000 stops (157 blocks) took 1.19 s with the pool and 1.63 s without, that
    of 150 stops (3 blocks, 164 parameters) 128 ms with it and 101 ms without."""
    workers = cpu_workers() if len(blocks) >= POOL_BLOCKS and _in_pieces() else 1
    if workers == 1:
        return [call(b) for b, _ in blocks]
    return list(_pool(workers).map(lambda bn: call(bn[0]), blocks))


def _joined(parts: list, blocks: list, per_stop: int) -> np.ndarray:
    """The blocks' outputs `parts` (one array a block, `per_stop` rows a stop) joined in
    numpy, without the rows of the last block's padding."""
    return np.concatenate([np.asarray(p)[: per_stop * n] for p, (_, n) in zip(parts, blocks)])


def _scales(G, mask):
    """Jacobi scaling D (P,) = mask / column norms of J, from the Gram matrix G = JᵀJ (P, P)
    (1 for a zero column)."""
    norms = np.sqrt(np.maximum(np.diag(G), 0.0))
    return np.where(norms > 0, 1.0 / np.where(norms > 0, norms, 1.0), 1.0) * mask


def _gram_step(G, g, rcond):
    """−A⁺ r from G = AᵀA (P, P) and g = Aᵀr (P,), singular values of A below `rcond` × the
    largest dropped, by the eigen-decomposition AᵀA = V Λ Vᵀ (σ² = λ): on the (N·6, P)
    Jacobian of a discovery fit (900 × 164) LAPACK's SVD takes 11 ms, forming AᵀA and `eigh`
    on it 3.8. The price: rounding is amplified by κ² (κ = σ_max / σ of the weakest kept
    direction) where an SVD amplifies it by κ, so a step along a direction kept at σ/σ_max =
    1e-4 is exact to ~1e-8 relative, and near the truncation level to ~1e-4; the next
    Gauss-Newton step corrects it. The columns of A are scaled to unit norm (`_scales`), so
    λ_max ≤ P and the truncation level rcond² λ_max (1e-12 λ_max) stays ~100× above the
    eigenvalues' rounding error (~P ε λ_max). A G or g that is not finite gives a step of
    NaN (the fit then stops there and `_fit_once` falls back to LM), not LAPACK's error."""
    return _TruncatedGram(G, g, rcond).step()


class _TruncatedGram:
    """The truncated Gauss-Newton model at one point (`_gram_step`): G = AᵀA (P, P) and
    g = Aᵀr (P,) in eigen-coordinates, directions with λ ≤ rcond² λ_max dropped. `step(μ)`
    is the damped step −(G + μ I)⁺ g on the kept directions (μ = 0: the Gauss-Newton step),
    `within(Δ)` the step of length at most Δ (the trust region's: the smallest μ that
    reaches it) and `reduction(p)` the decrease of |r + A p|² the model predicts."""

    def __init__(self, G, g, rcond):
        self.finite = bool(np.all(np.isfinite(G)) and np.all(np.isfinite(g)))
        if not self.finite:
            self.size = np.shape(g)[0]
            return
        lam, self.V = np.linalg.eigh(G)
        self.keep = lam > rcond**2 * (lam[-1] if lam.size else 0.0)  # (no free parameter)
        self.lam = np.where(self.keep, lam, 1.0)
        self.c = np.where(self.keep, self.V.T @ g, 0.0)  # g in eigen-coordinates, kept

    def step(self, mu=0.0):
        if not self.finite:
            return np.full(self.size, np.nan)
        return -self.V @ (self.c / (self.lam + mu))

    def solve(self, b, mu=0.0):
        """−(G + μI)⁺ b on the kept directions."""
        return -self.V @ (np.where(self.keep, self.V.T @ b, 0.0) / (self.lam + mu))

    def within(self, radius):
        """(step, μ): the Gauss-Newton step where it is no longer than `radius`, else the
        damped step of length `radius` (to 1 %; Newton's method on 1/|p(μ)|, which is
        nearly linear in μ, from μ = 0: monotone, a few iterations)."""
        mu = 0.0
        for _ in range(50):  # iterations of a scalar equation, not a loop over data
            d = self.lam + mu
            norm = np.sqrt(np.sum((self.c / d) ** 2))
            if norm <= 1.01 * radius:
                break
            mu += norm**2 / np.sum(self.c**2 / d**3) * (norm - radius) / radius
        return self.step(mu), mu

    def reduction(self, p):
        """|r|² − |r + A p|² = −2 gᵀp − pᵀ G p, from the eigen-coordinates of p."""
        y = np.where(self.keep, self.V.T @ p, 0.0)
        return float(-2 * self.c @ y - np.sum(self.lam * y**2))


def _truncated_step(A, r, rcond):
    """−A⁺ r for A (M, P), r (M,): `_gram_step` of AᵀA and Aᵀr."""
    A, r = np.asarray(A), np.asarray(r)
    return _gram_step(A.T @ A, A.T @ r, rcond)


def _gauss_newton(problem, layout, theta0, mask, rtol, atol, max_steps, rcond=1e-6, prior=None):
    """Gauss-Newton in Jacobi-scaled variables u (θ = θ0 + D·u, D = `_scales` of the
    Jacobian at θ0) with truncated least-squares steps (`_gram_step`): singular values
    below `rcond` × the largest (frozen, i.e. masked, and unidentifiable directions) get no
    step, so those parameters stay at their start values instead of drifting.

    Steps are kept within a trust region (Moré's Levenberg-Marquardt: the damped step
    −(G + μI)⁺g of length Δ, `_TruncatedGram.within`). Δ starts unbounded, so where every
    Gauss-Newton step lowers χ² = |r|² the fit takes exactly those steps. A step that does
    not lower χ² (ρ = actual / predicted decrease ≤ 1e-4, unless the predicted decrease
    and any increase are at the rounding of χ², 1e-10 relative), or leaves a weighted row
    without a forward solution, is not taken: Δ becomes 0.1–0.5 of its length (where a
    quadratic through χ² along it has its minimum) and the step is taken again from the
    same point with the same Jacobian. A taken step with ρ < 0.25 halves Δ; with ρ > 0.75,
    Δ grows to at least 2 step lengths. A step not taken is first bent by geodesic
    acceleration (Transtrum & Sethna 2012; the residual's second derivative along it from
    the evaluation just made) and the bent step taken where it lowers χ²: along the curved
    valley of an x interferometer on a line the straight steps alternated between taken and
    shortened and ran out of steps. On data that barely determine some directions (a
    6-D tracker on an x line), an undamped step went ~1e5 scaled units along directions
    just above the truncation level, where the linearisation does not hold (χ² 45,000 →
    1.5e12), and never came back.

    Each evaluation computes the residual and its Jacobian once, in blocks of `FIT_BLOCK`
    stops (`jacobian_in_chunks`: one compiled program whatever the number of stops, so a
    file of a new length fits without compiling); the step is a P × P eigen-decomposition
    of the Gram matrix, formed in numpy (for 900 × 164 in 0.8 ms, where XLA's CPU product
    took 3.6). The start's Jacobian sets D; the last one is the Jacobian at the returned θ
    (at least one is evaluated, whatever `max_steps`; `max_steps` counts evaluations, the
    steps not taken included). Stopping rule: optimistix's Cauchy rule for its
    `GaussNewton` on the points taken: stop at u_k when max|u_k − u_k−1| / (atol +
    rtol·|u_k|) < 1 and max|r_k − r_k−1| / (atol + rtol·|r_k|) < 1; also where a step not
    taken was itself within the first bound (no smaller step can lower χ² by more than
    rounding), and at the second point in a row where the Gauss-Newton step predicts a
    decrease within the rounding of χ² (1e-10 relative). Without that last rule, fits along
    directions the data barely determine (an x interferometer on a line) took their 200
    steps at the optimum: the residual's rounding, amplified by 1/σ along those
    directions, moved them by more than the first bound at every step.

    `prior` (P,): 1 / σ of a Gaussian prior N(0, σ²) on each flat parameter (0: none;
    `prior.weights`), entered as the pseudo-observations prior·f: χ² and the Gram matrix
    and gradient of every step include them (G + Λ, g + Λ f with Λ = diag(prior²)); J and
    the residuals returned are the data's. Only free parameters (`mask`) take it.

    The step's model holds the free parameters' columns only: a parameter frozen by `mask`
    has D = 0, so its row and column of the scaled Gram matrix are zero and it takes no step
    (the full matrix's eigen-decomposition gave it none either). The diagnosis fits nested
    models on one canonical parameter vector (170 parameters for the bundled example, 42–61
    of them free): an eigen-decomposition of the free block costs ~(F/P)³ of the full one's.

    Returns (θ, converged, steps, J at θ, solved (N,), residual at θ0, residual at θ), numpy
    arrays and θ as `theta0`'s pytree."""
    flat0, mask = _flat(theta0), np.asarray(mask, float)
    lam = np.zeros_like(mask) if prior is None else (np.asarray(prior, float) * mask) ** 2
    blocks = _stop_blocks(problem, layout)
    weighted = np.asarray(problem.weight).any(axis=1)
    free = np.flatnonzero(mask)  # the model's parameters: p, D and G below are over these

    def evaluate(f):
        J, r, solved = jacobian_in_chunks(problem, layout, theta0, flat=f, blocks=blocks)
        ok = np.all(np.asarray(solved)[weighted]) and np.all(np.isfinite(r))
        return J, r, solved, float(r @ r + lam @ f**2) if ok else np.inf

    def gram(J):  # the model's matrix over the free columns, the prior's pseudo-observations in it
        A = J[:, free]
        return A.T @ A + np.diag(lam[free]), A

    def scaled(x):  # free parameters' values (or differences) in the scaled variables
        return x[free] / D  # (D > 0 on every free parameter: `_scales` of a nonzero mask)

    def moved(f, p):  # f (P,) moved by the scaled step p of the free parameters
        out = f.copy()
        out[free] += D * p
        return out

    J, r, solved, chi2 = evaluate(flat0)
    G, A = gram(J)
    D, r0 = _scales(G, mask[free]), r
    f, k, done, radius, flat = flat0, 1, False, np.inf, False
    while not done and k < max_steps:
        g = D * (A.T @ r + lam[free] * f[free])
        model = _TruncatedGram(D[:, None] * G * D[None, :], g, rcond)
        was_flat, flat = flat, model.reduction(model.step()) <= 1e-10 * chi2
        if was_flat and flat:  # twice nothing to gain beyond rounding: converged
            done = True
            break
        p, mu = model.within(radius)
        if not np.all(np.isfinite(p)):
            break
        trial = moved(f, p)
        J_t, r_t, solved_t, chi2_t = evaluate(trial)
        k += 1
        predicted = model.reduction(p)
        rho = (chi2 - chi2_t) / predicted if predicted > 0 else -np.inf
        # a decrease the model puts at the rounding of χ² (the forward solves' tolerance:
        # ~1e-11 relative) cannot be tested: such a step is taken, as it would be undamped
        rounding = max(predicted, chi2_t - chi2) <= 1e-10 * chi2
        if not (rho > 1e-4 or rounding) and np.isfinite(chi2_t) and k < max_steps:
            # geodesic acceleration (Transtrum & Sethna): the residual's second derivative
            # along p from the step just evaluated, r(f + p) = r + J p + r_pp / 2 + ...,
            # bends the step along a curved valley: p + a/2, a = −(G + μI)⁺ Jᵀ r_pp
            r_pp = 2 * (r_t - r - A @ (D * p))
            a = model.solve(D * (A.T @ r_pp), mu)
            if 2 * np.linalg.norm(a) <= 0.75 * np.linalg.norm(p):  # their bound
                bent = p + 0.5 * a
                J_b, r_b, solved_b, chi2_b = evaluate(moved(f, bent))
                k += 1
                if chi2_b < chi2:  # taken, with Δ as for a fair step (ρ of 0.26 at least)
                    p, trial = bent, moved(f, bent)
                    J_t, r_t, solved_t, chi2_t = J_b, r_b, solved_b, chi2_b
                    predicted = model.reduction(p)
                    rho = max((chi2 - chi2_t) / predicted, 0.26) if predicted > 0 else 0.26
        length = np.sqrt(p @ p)
        small_u = np.max(np.abs(p) / (atol + rtol * np.abs(scaled(trial - flat0))), initial=0.0) < 1
        if not (rho > 1e-4 or rounding):  # not taken (also a χ² of inf or NaN)
            done = small_u
            slope = -2 * predicted  # ≈ d χ²/dt along p at t = 0 (the model's, for t ≪ 1)
            curve = chi2_t - chi2 - slope
            t = -slope / (2 * curve) if np.isfinite(curve) and curve > 0 else 0.1
            radius = float(np.clip(t, 0.1, 0.5)) * length
            continue
        small_r = np.max(np.abs(r_t - r) / (atol + rtol * np.abs(r_t)), initial=0.0) < 1
        done = small_u and small_r
        if rho < 0.25:
            radius = 0.5 * length
        elif rho > 0.75:
            radius = max(radius, 2 * length)
        f, J, r, solved, chi2 = trial, J_t, r_t, solved_t, chi2_t
        G, A = gram(J)
    return _unflat(theta0, f), done, k, J, solved, r0, r


@jit
def _levenberg_marquardt(
    problem, layout, theta0, D, rtol, atol, max_steps, prior, method="levenberg_marquardt"
):
    """optimistix Levenberg-Marquardt in the scaled variables of `_gauss_newton`, the
    prior's pseudo-observations `prior` (P,) · f after the data's residuals (zeros: none).
    Returns (θ, converged, steps)."""
    flat0, unravel = ravel_pytree(theta0)

    def res_scaled(u, _):
        f = flat0 + D * u
        return jnp.concatenate([residual(unravel(f), (problem, layout)), prior * f])

    sol = optx.least_squares(
        res_scaled,
        optx.LevenbergMarquardt(rtol=rtol, atol=atol),
        jnp.zeros_like(flat0),
        None,
        max_steps=max_steps,
        throw=False,
    )
    value = unravel(flat0 + D * sol.value)
    return value, sol.result == optx.RESULTS.successful, sol.stats["num_steps"]


def _solve(
    problem,
    layout,
    theta0,
    mask,
    rtol,
    atol,
    max_steps,
    method="gauss_newton",
    rcond=1e-6,
    prior=None,
):
    """Fit in Jacobi-scaled variables (θ = θ0 + D·mask·u, D = 1 / column norms of the
    Jacobian at θ0): mm, rad and mm/rev parameters then take comparable steps. `mask` (P,)
    (0/1, traced) freezes parameters without recompiling, so nested models and folds of one
    data set share one compilation. "gauss_newton": `_gauss_newton`, one compiled program per
    model structure, whatever the number of stops; "levenberg_marquardt": optimistix's LM
    between two Jacobian evaluations (the start's sets D).

    `prior` (P,): 1 / σ of a Gaussian prior on each parameter (`_gauss_newton`).

    Returns (θ, converged, steps, J at θ, solved (N,), residual at θ0, residual at θ)."""
    if method == "gauss_newton":
        return _gauss_newton(problem, layout, theta0, mask, rtol, atol, max_steps, rcond, prior)
    mask = np.asarray(mask, float)
    w = np.zeros_like(mask) if prior is None else np.asarray(prior, float) * mask
    J0, r0, _ = jacobian_in_chunks(problem, layout, theta0)
    D = jnp.asarray(_scales(J0.T @ J0 + np.diag(w**2), mask))
    value, converged, steps = _levenberg_marquardt(
        problem, layout, theta0, D, rtol, atol, max_steps, jnp.asarray(w)
    )
    J, r, solved = jacobian_in_chunks(problem, layout, value)
    return value, converged, steps, J, solved, r0, r


def _session_times(problem: Problem, rows: np.ndarray, n_sessions: int) -> np.ndarray:
    """(S, 2) the file's time (`Context.time`) of each session's first and last row of
    `rows` (N,) bool (0, 0 for a session without such rows)."""
    t, s = np.asarray(problem.ctx.time, float), np.asarray(problem.session)
    lo, hi = np.full(n_sessions, np.inf), np.full(n_sessions, -np.inf)
    np.minimum.at(lo, s[rows], t[rows])
    np.maximum.at(hi, s[rows], t[rows])
    empty = hi < lo
    return np.stack([np.where(empty, 0.0, lo), np.where(empty, 0.0, hi)], axis=1)


def _kabsch(P, Q):
    """Rotation R and translation t minimising |R P + t − Q| over rows (P, Q (N, 3))."""
    pc, qc = P.mean(0), Q.mean(0)
    R, S = best_rotation(P - pc, Q - qc)
    if S[1] < 1e-9 * max(S[0], 1e-300):  # collinear points: no rotation information
        return np.eye(3), qc - pc
    return R, qc - R @ pc


def initial_frames(data: Measurements, frame_dofs, predicted=None) -> np.ndarray:
    """Closed-form instrument frames (S, 6) per session: rigid registration (Kabsch) of the
    measured positions against the commanded ones (or `predicted` (N, 6) readings in the base
    frame) over the rows that read all three positions, when the frame has all six DOFs;
    otherwise the mean offset of each measured translation column. Lost cells (NaN) are not
    measured: they never enter a sum. A session with fewer than 3 complete rows gets its
    offsets only (rotation 0)."""
    out = np.zeros((len(data.sessions), 6))
    idx = data.session_index
    ref = data.cmd_pose if predicted is None else np.asarray(predicted)
    for k in range(len(data.sessions)):
        rows = idx == k
        P = ref[rows, :3]
        Q = data.measured[rows, :3]
        complete = np.isfinite(Q).all(axis=1)
        if len(frame_dofs) == 6 and complete.sum() >= 3:
            R, t = _kabsch(P[complete], Q[complete])
            out[k, :3] = t
            out[k, 3:] = euler_from_matrix(R)
        else:
            for c in frame_dofs:
                if c < 3 and np.isfinite(Q[:, c]).any():
                    out[k, c] = np.nanmean(Q[:, c] - P[:, c])
    return out


@dataclass
class Calibration:
    """Result of `calibrate`. `table`, `effects`: the fitted model; `frame` (S, 6) instrument
    frames per session and `target` (6,) (mm / rad); `names` of the fitted parameters (stable
    keys; joint sets fitted modulo rigid motions appear as their non-rigid components
    `base_joints.g1..12`) and their physical `labels`; `value`, `std` and `correlation` of
    them (std = inf for an unidentifiable direction); `singular_values` of the column-scaled
    weighted Jacobian; `unidentifiable`: list of (singular value, [(label, weight), ...]) for
    each direction the data cannot determine; `chi2`, `dof`; `converged`, `steps`.

    RMS, in the same form as `Diagnosis`: `rms_sigma_before` / `rms_sigma_after` (RMS of the
    σ-normalised residuals, 1.0 = at the noise) and `rms_columns_before` /
    `rms_columns_after` (per measured column, mm / rad); `rms_before` / `rms_after` are the
    per-column ones under their earlier names."""

    table: Table
    effects: dict
    frame: np.ndarray
    target: np.ndarray
    names: list
    value: np.ndarray
    std: np.ndarray
    correlation: np.ndarray
    singular_values: np.ndarray
    unidentifiable: list
    rms_before: dict
    rms_after: dict
    chi2: float
    dof: int
    converged: bool
    steps: int
    layout: Layout
    bases: dict = field(default_factory=dict)
    theta: dict = field(default_factory=dict)
    effects_nominal: dict = field(default_factory=dict)
    rank: int = 0
    n_obs: int = 0
    residual: np.ndarray | None = None  # (N, 6) weighted residuals after the fit
    covariance: np.ndarray | None = None
    jacobian: np.ndarray | None = None  # (N·6, P) weighted residual Jacobian, free columns
    # (N·6,) redundancy numbers 1 − H_ii of the fit's hat matrix (`noise.redundancy` of
    # `jacobian`, from the identifiability analysis's SVD; 0 for observations not used)
    redundancy: np.ndarray | None = None
    # (N·6, P_all): the same over every parameter of the set-up (`Setup.names`), frozen ones
    # included: what freeing a parameter would add (the discovery dictionary's screening)
    jacobian_full: np.ndarray | None = None
    weight: np.ndarray | None = None  # (N, 6) the weights 1/σ of the fit (all rows)
    noise: NoiseEstimate | None = None
    labels: list = field(default_factory=list)
    rows_skipped: int = 0  # rows with nothing measured (not fitted)
    rms_sigma_before: float = float("nan")
    rms_sigma_after: float = float("nan")
    # readings set aside as gross errors before this fit (`outliers.GrossError`, largest
    # first), and how many readings the screen could not test (redundancy too low); None:
    # not screened (outliers="keep", or a fit not made by `calibrate`)
    set_aside: list | None = None
    untested: int = 0
    crowded: int = 0  # readings beyond the bound whose neighbours are too: structure, kept
    # rows that repeat an earlier row exactly (a stop logged twice: `outliers.Repeat`), set
    # aside with the readings above
    repeated: list = field(default_factory=list)
    # stops read more than once (`stops.Stops`), each fitted once at the mean of its
    # readings; None: one row a stop
    stops: object | None = None
    # the data as fitted (`fit_screened`: rows set aside, stops merged); None: `data`
    data: Measurements | None = field(default=None, repr=False)
    screen_skipped: str = ""  # why the screen did not run (structure the model misses)
    # where it did not run for structure: the readings its trial found far from their
    # neighbours (`outliers.GrossError`, measured − this fit's model, largest first), kept in
    # the fit: gross errors on top of the structure, or its peaks
    suspects: list = field(default_factory=list)
    # where the screen did not run for structure: a step in time within a session that
    # explains it (`_discovery.changepoint.StepInTime`, found), else None
    step: object | None = None
    # with a prior from the tolerances (`calibrate(..., prior=)`): its σ (P,) for each
    # fitted parameter (inf: none), and its share of the fit's objective, Σ (θ / σ)²; `std`
    # and `covariance` are then the posterior's, `chi2` the data's alone
    prior_sigma: np.ndarray | None = None
    chi2_prior: float = 0.0
    # (S, 6) mm / rad: each session's instrument frame drift from the file's time 0 to 1
    # (`Context.time`; the frame at a row is `frame` + `frame_drift` · time), where the fit
    # had one (`setup(..., frame_drift=True)`); None: the frames held still. `session_time`
    # (S, 2): the file's time of each session's first and last measured row
    frame_drift: np.ndarray | None = None
    session_time: np.ndarray | None = None

    @property
    def session_span(self) -> np.ndarray | None:
        """(S,) the file's time each session's measured rows span, first to last."""
        t = self.session_time
        return None if t is None else np.asarray(t)[:, 1] - np.asarray(t)[:, 0]

    def frames_at_end(self) -> np.ndarray:
        """(S, 6) each session's instrument frame at its last measured row: `frame`, moved
        by its drift where the fit had one (where the instrument was when the data ended)."""
        if self.frame_drift is None or self.session_time is None:
            return np.asarray(self.frame, float)
        end = np.asarray(self.session_time)[:, 1:]
        return np.asarray(self.frame, float) + np.asarray(self.frame_drift) * end

    def frame_drift_changes(self) -> dict:
        """{`frame_drift[s].dof`: (session s, frame DOF, change, σ)} where the fit had the
        instrument frame drift: each free drift parameter's change over its session, first
        row to last (mm / rad); {} without a drift."""
        if self.frame_drift is None:
            return {}
        out = {}
        for s in range(np.shape(self.frame_drift)[0]):
            span = 1.0 if self.session_span is None else float(self.session_span[s])
            for d in self.layout.frame_dofs:
                key = f"frame_drift[{s + 1}].{params.POSE[d]}"
                if key in self.names:
                    i = self.names.index(key)
                    out[key] = (s, d, float(self.value[i]) * span, float(self.std[i]) * span)
        return out

    def frame_drift_lines(self) -> list:
        """A line a session where the fit had the instrument frame drift
        (`frame_drift_changes`): its fitted change over the session, first row to last,
        each DOF ± σ."""
        changes = self.frame_drift_changes()
        lines = []
        for s in sorted({c[0] for c in changes.values()}):  # sessions, not data
            span = 1.0 if self.session_span is None else float(self.session_span[s])
            parts = [params.change_words(d, v, sd) for t, d, v, sd in changes.values() if t == s]
            if parts and span > 0:
                lines.append(
                    f"instrument frame drift over session {s + 1}, first row to last (a "
                    f"nuisance of these data, not in the model): {', '.join(parts)}"
                )
        return lines

    def group_sigma(self) -> dict:
        """{"positions" | "angles": the σ the fit found for the group} (mm / rad), the
        groups the noise model has by those names."""
        if self.noise is None:
            return {}
        return {
            g: float(s)
            for g, s in zip(self.noise.names, np.asarray(self.noise.sigma))
            if g in ("positions", "angles")
        }

    @property
    def prior_share(self) -> np.ndarray | None:
        """(P,) with a prior: (σ / prior σ)² of each fitted parameter, the share of its
        prior variance left after the data (1: the data say nothing of it, 0: they fix
        it; NaN where it has no prior); None without a prior."""
        if self.prior_sigma is None:
            return None
        with np.errstate(invalid="ignore"):
            return np.where(
                np.isfinite(self.prior_sigma), (self.std / self.prior_sigma) ** 2, np.nan
            )

    def light(self) -> "Calibration":
        """This fit without its arrays of a row per observation and a column per parameter
        (`jacobian`, `jacobian_full`, `redundancy`): the record a search keeps of a fit it
        has scored. Values, σ, covariance, residuals and weights stay; on 10,000 stops the
        dropped arrays hold ~0.3 GB a fit."""
        return dataclasses.replace(self, jacobian=None, jacobian_full=None, redundancy=None)

    @property
    def rms_columns_before(self) -> dict:
        return self.rms_before

    @property
    def rms_columns_after(self) -> dict:
        return self.rms_after

    def parameter(self, prefix: str):
        """(value, std) arrays of the fitted parameters whose name starts with `prefix`
        (e.g. "spiral.lead")."""
        idx = [i for i, n in enumerate(self.names) if n == prefix or n.startswith(prefix + "[")]
        return self.value[idx], self.std[idx]

    def _undetermined_lines(self) -> list:
        """What the combinations the data cannot determine do to the fitted values: every
        parameter with weight on one has σ = inf, and its value is where the fit left it."""
        inf = np.isinf(self.std)
        if not inf.any():
            return []
        mm = [i for i in np.flatnonzero(inf) if self.names[i].startswith(params.GEOMETRY)]
        far = max(mm, key=lambda i: abs(self.value[i]), default=None)
        where = (
            ""
            if far is None
            else f" (the largest geometric change: {params.short_label(self.labels[far])} "
            f"{self.value[far]:+.4g} mm)"
        )
        return [
            f"so {int(inf.sum())} of the {len(self.std)} fitted parameters have σ = inf: "
            f"their values are not determined by the data{where}; the fit reproduces these "
            "readings, but a table fitted along such combinations predicts other poses and "
            "columns poorly: free fewer parameters, or measure where they act"
        ]

    def _prior_lines(self) -> list:
        """What the prior from the tolerances did: how many parameters it holds, how many
        the data determine, and whether the fit stayed within the tolerances."""
        if self.prior_sigma is None:
            return []
        on = np.isfinite(self.prior_sigma)
        share = self.prior_share[on]
        x, expected, p = prior_check(self.value, self.covariance, self.prior_sigma)
        idx = np.flatnonzero(on)
        best = idx[np.argsort(share)[:3]]
        named = ", ".join(
            f"{params.short_label(self.labels[i])} σ {self.std[i]:.3g} of {self.prior_sigma[i]:.3g}"
            for i in best
            if self.prior_share[i] < 0.5
        )
        lines = [
            f"prior (tolerances): {int(on.sum())} of the {len(on)} fitted parameters held "
            "within their tolerances around the nominal table; σ are the posterior's: "
            f"{int(np.sum(share < 0.5))} keep less than half their prior variance (the data "
            f"determine them{': ' + named if named else ''}), {int(np.sum(share > 0.9))} "
            "more than 90 % (set by the tolerances, not by the data)",
            f"prior check: Σ (change / tolerance)² = {x:.3g}, {expected:.3g} expected of a "
            f"table built to its tolerances (p = {p:.2g})"
            + (
                ": the data pull the geometry beyond its tolerances: the table is not built "
                "to them, or the model lacks an effect the geometry takes up (`jaxtable "
                "diagnose`)"
                if p < 0.001
                else ": within them"
            ),
        ]
        return lines

    def report(self) -> str:
        lines = [
            f"converged: {self.converged} ({self.steps} steps); chi2/dof = "
            f"{self.chi2:.1f}/{self.dof} = {self.chi2 / max(self.dof, 1):.3f}",
            f"RMS of residuals / sigma (before -> after): {self.rms_sigma_before:.3f} -> "
            f"{self.rms_sigma_after:.3f} (1.0 = at the "
            + ("estimated" if self.noise is not None and self.noise.estimated else "stated")
            + " noise)",
            "RMS residual per measured column, mm / rad (before -> after): "
            + ", ".join(
                f"{c} {self.rms_before[c]:.4g} -> {self.rms_after[c]:.4g}" for c in self.rms_after
            ),
        ]
        if self.repeated:
            lines.append(repeat_words(self.repeated))
        if self.data is not None:
            alias = instrument_scale(self, np.isfinite(np.asarray(self.data.measured, float)))
            if alias is not None:
                lines.append(alias.words())
        if self.stops is not None:
            lines.append(self.stops.words(self.group_sigma()))
        if self.noise is not None:
            lines += self.noise.lines()
        # repeated rows and a stop's rows after its first are among the rows skipped
        merged = len(self.repeated) + (
            0 if self.stops is None else self.stops.rows - self.stops.stops
        )
        if self.rows_skipped > merged:
            other = " other" if merged else ""
            lines.append(
                f"{self.rows_skipped - merged}{other} row(s) with nothing measured: skipped"
            )
        if self.set_aside:
            shown = "; ".join(g.words() for g in self.set_aside[:10])
            more = f"; ... and {len(self.set_aside) - 10} more" if len(self.set_aside) > 10 else ""
            lines.append(
                f"{len(self.set_aside)} reading(s) set aside as gross errors (measured − "
                f"model, in robust σ; family-wise false-alarm rate {ALPHA:g}): {shown}{more}; "
                "fitted without them (outliers='keep' / --keep-outliers fits every reading)"
            )
        elif self.screen_skipped.startswith("the structure test needs"):
            lines.append(f"gross errors: not screened ({self.screen_skipped})")
        elif self.screen_skipped:
            lines.append(
                "gross errors: not screened: the residuals show structure the model misses ("
                + self.screen_skipped
                + "), and a gross error cannot be told from it; fit a model that explains "
                "them (jaxtable diagnose)"
            )
            if self.suspects:
                lines.append(
                    f"{len(self.suspects)} reading(s) far from their neighbours, kept in this "
                    "fit (gross errors on top of the structure, or its peaks; check them): "
                    + "; ".join(g.words() for g in self.suspects[:10])
                    + (
                        f"; ... and {len(self.suspects) - 10} more"
                        if len(self.suspects) > 10
                        else ""
                    )
                )
        elif self.set_aside is not None:
            lines.append("gross errors: none (every reading agrees with the fit)")
        if self.step is not None:
            lines.append(
                f"{self.step.words()}: mark rows {self.step.row}… of session "
                f"{self.step.session} as a session of their own (jaxtable diagnose does)"
            )
        if self.set_aside is not None and self.crowded:
            lines.append(
                f"{self.crowded} reading(s) far from the model whose neighbours (in time and in "
                "the legs' extensions) are far out the same way: structure the model misses, "
                "not gross errors; kept"
            )
        if self.set_aside is not None and self.untested:
            lines.append(
                f"{self.untested} reading(s) the fit would absorb whatever their error "
                "(redundancy < 0.05): not tested for gross errors"
            )
        lines += self.frame_drift_lines()
        if self.layout.frame_dofs and len(self.layout.frame_dofs) < 6:
            seen = [params.POSE[k] for k in self.layout.frame_dofs]
            unseen = [c for k, c in enumerate(params.POSE) if k not in self.layout.frame_dofs]
            lines.append(
                f"instrument frame: {', '.join(seen)} estimated; {', '.join(unseen)} "
                "unobservable with the measured columns"
            )
        if self.layout.gauge:
            lines.append(
                "gauge: " + ", ".join(self.layout.gauge) + " fitted modulo rigid motions "
                "(absorbed by the instrument frame / target offset)"
            )
        if self.unidentifiable:
            lines.append(
                f"{len(self.unidentifiable)} parameter combination(s) this instrument "
                "and pose plan cannot determine:"
            )
            for sv, parts in self.unidentifiable[:12]:
                lines.append(
                    f"  - (singular value {sv:.1e}) "
                    + " ".join(f"{w:+.2f}*({params.short_label(n)})" for n, w in parts)
                )
            if len(self.unidentifiable) > 12:
                lines.append(f"  ... and {len(self.unidentifiable) - 12} more")
            lines += self._undetermined_lines()
        else:
            lines.append(
                "every fitted parameter is identifiable from these data"
                + (" and the prior" if self.prior_sigma is not None else "")
            )
        lines += self._prior_lines()
        for k, pitch in enumerate(np.degrees(np.asarray(self.frame)[:, 4])):
            if abs(abs(pitch) - 90.0) < 1.0:  # the frame's Euler angles at gimbal lock
                lines.append(
                    f"the instrument frame of session {k + 1} is pitched {pitch:.2f}°: there "
                    "its roll and yaw turn about nearly one axis (the Euler angles' gimbal "
                    "lock), so their sum or difference is poorly determined whatever the "
                    "data, and the fit may take many steps; the frame as a rotation is "
                    "determined (define the instrument's axes so that its pitch to the "
                    "base is far from ±90° to avoid it)"
                )
        return "\n".join(lines)


def hardware_table(cal: "Calibration") -> Table:
    """The fitted table with a fitted spiral lead written back as hardware: `lead` = |lead|,
    `hand` = its sign (what a table file stores)."""
    table = cal.table
    if "spiral" in cal.effects:
        lead = np.asarray(cal.effects["spiral"].lead)
        table = replace(table, lead=np.abs(lead), hand=np.where(lead < 0, -1.0, 1.0))
    return table


def sigma_rms(weighted: np.ndarray, mask: np.ndarray) -> float:
    """RMS of σ-normalised residuals (N, 6) over the measured cells `mask` (N, 6)."""
    r = np.asarray(weighted)[mask]
    return float(np.sqrt(np.mean(r**2))) if r.size else float("nan")


def zero_steps(nominal: Table, effects: dict, free, bases: dict) -> dict:
    """θ0: a zero step for every free parameter block (joint sets in their basis)."""
    return {  # zeros made in numpy (an eager jnp.zeros compiles a program per shape)
        name: device_array(
            np.zeros(bases[name].shape[1])
            if name in params.JOINTS
            else np.zeros(())
            if params.is_shared(name)
            else np.zeros(np.shape(params.get(nominal, effects, name)))
        )
        for name in free
    }


def parameter_keys(layout: Layout, theta0: dict, bases: dict) -> tuple[list, list]:
    """(keys, labels) of the flat parameters, in `ravel_pytree` order (dict keys sorted).
    Keys are stable (`zero_lengths[3]`, `base_joints.g7` for a joint set's coordinate in its
    basis, `frame[1].yaw`, `target.z`); labels are physical (`jaxtable._params.label`), a
    gauge coordinate's label naming the joint displacements it moves."""
    keys, labels = [], []
    for key in sorted(theta0):
        v = np.asarray(theta0[key])
        if key in params.JOINTS:
            basis = np.asarray(bases[key])
            gauged = key in layout.gauge
            for i in range(v.size):
                keys.append(f"{key}.g{i + 1}")
                labels.append(
                    params.gauge_label(key, i, basis)
                    if gauged
                    else params.label(params.element_keys(key, (6, 3))[i])
                )
            continue
        if key in ("frame", "frame_drift"):
            new = [
                f"{key}[{s + 1}].{params.POSE[d]}"
                for s in range(v.shape[0])
                for d in layout.frame_dofs
            ]
        elif key == "target":
            new = [f"target.{params.POSE[d]}" for d in layout.target_dofs]
        else:
            new = params.element_keys(key, v.shape)
        keys += new
        labels += [params.label(k) for k in new]
    return keys, labels


def data_context(data: Measurements, cmd: np.ndarray, uses=("temperature", "mass")) -> Context:
    """Batched context (N,) of the data's stops: direction of travel from the row order of
    the commanded lengths `cmd` (N, 6), temperature (20 °C if absent), payload (0 kg if
    absent), session index.

    A blank temperature (payload) cell where the model uses that column (`uses` holds
    "temperature" for the thermal effect, "mass" for compliance) is refused with its row
    named: never a NaN that surfaces as a failed solve. Where no effect of the model uses the
    column, blanks take the reference value (20 °C, 0 kg), which no effect then reads."""
    n = len(data)
    columns = {
        "temperature": (data.temperature, 20.0, "temperature", "thermal"),
        "mass": (data.payload, 0.0, "payload", "compliance"),
    }
    values = {}
    for need, (col, ref, name, effect) in columns.items():
        if col is None:
            values[need] = np.full(n, ref)
            continue
        v = np.asarray(col, float)
        blank = ~np.isfinite(v)
        if blank.any() and need in uses:
            rows = (np.flatnonzero(blank) + 1).tolist()
            raise ValueError(
                f"row {rows[0]}, column '{name}': blank cell, and the {effect} effect uses "
                f"that column ({len(rows)} blank row(s): {rows[:10]}); fill it or drop the "
                f"row(s)"
            )
        values[need] = np.where(blank, ref, v)
    return Context(
        directions(cmd),
        values["temperature"],
        values["mass"],
        np.asarray(data.session_index),
        run_time(len(cmd), data.time, data.session_index),
    )


def used_columns(effects: dict, free) -> set:
    """Data columns the model reads ("temperature", "session", "mass"): the `needs` of every
    effect that is fitted (a field in `free`) or not at its null value."""
    out = set()
    for name, eff in effects.items():
        fitted = any(params.split(f)[0] == name for f in free)
        active = any(np.any(np.asarray(x) != 0) for x in jax.tree.leaves(eff))
        if fitted or active:
            out |= set(type(eff).needs)
    return out


COMPENSATION_UNKNOWN = (
    "the data have no commanded lengths (cmd_l1..cmd_l6) and the table has a screw lead, so "
    "the commands depend on whether the controller compensated the passive spiral term "
    "(0.26 mm apart on the paper's x stroke): say which with --compensated or "
    "--uncompensated (compensated=True / False in Python)"
)


def commanded_lengths(nominal: Table, data: Measurements, compensated: bool | None) -> np.ndarray:
    """(N, 6) joint-to-joint lengths the controller commanded: the file's cmd_l columns, or
    the nominal inverse kinematics of the commanded poses, compensated for the spiral term
    when `compensated`. One rule for every verb: without cmd_l columns on a table with a
    lead, `compensated` must be stated (ValueError otherwise)."""
    if data.cmd_lengths is not None:
        return np.asarray(data.cmd_lengths, float)
    if compensated is None:
        if np.any(np.asarray(nominal.lead) != 0):
            raise ValueError(COMPENSATION_UNKNOWN)
        compensated = False
    return np.asarray(actuator_command(nominal, data.cmd_pose, compensated, check=False))


def make_problem(
    nominal: Table,
    data: Measurements,
    effects,
    bases,
    compensated: bool | None = None,
    uses=("temperature", "mass"),
    sigma0: np.ndarray | None = None,
):
    """Arrays of a calibration problem; refuses commands outside the stroke (row, leg named).
    `sigma0` (N, 6): σ of the measured cells the weights start from (default: the file's σ
    where stated, else `noise.DEFAULT_SIGMA`)."""
    mask = np.isfinite(data.measured)
    cmd = commanded_lengths(nominal, data, compensated)
    lo, hi = (float(v) for v in np.asarray(nominal.stroke))
    bad = np.argwhere(~np.asarray(in_stroke(nominal, cmd)) | ~np.isfinite(cmd))
    if len(bad):
        r, leg = bad[0]
        raise ValueError(
            f"row {r + 1}: commanded length of leg {leg + 1} ({cmd[r, leg]:.3f} mm) is outside "
            f"the stroke [{lo}, {hi}]" + (f" ({len(bad)} such cells)" if len(bad) > 1 else "")
        )
    sigma = sigma0
    if sigma is None:
        sigma = noise_model(
            data.measured,
            data.sigma,
            session=data.session_index,
            sessions=data.sessions,
            relative=data.relative_sigma,
        ).sigma0
    return Problem(
        nominal=nominal,
        start=nominal,
        effects=effects,
        s=device_array(cmd - np.asarray(nominal.zero_lengths)),
        guess=device_array(data.cmd_pose),
        measured=device_array(np.where(mask, data.measured, 0.0)),
        weight=device_array(np.where(mask, 1.0 / np.where(mask, sigma, 1.0), 0.0)),
        session=device_array(data.session_index),
        bases={n: device_array(b) for n, b in bases.items()},
        ctx=data_context(data, cmd, uses),
    )


def validate(
    cal: "Calibration", nominal: Table, data: Measurements, compensated: bool | None = None
) -> dict:
    """RMS residual per measured column (mm / rad) of the calibrated model on `data` (e.g.
    held-out poses), in the calibration's instrument frames (sessions matched by order of
    first appearance)."""
    problem = make_problem(nominal, data, cal.effects_nominal, cal.bases, compensated)
    res = weighted_residual(problem, cal.layout, cal.theta)
    mask = np.isfinite(data.measured)
    w = np.asarray(problem.weight)
    phys = np.where(mask, res / np.where(mask, w, 1.0), np.nan)
    return {
        c: float(np.sqrt(np.nanmean(phys[:, k] ** 2)))
        for k, c in enumerate("x y z roll pitch yaw".split())
        if mask[:, k].any()
    }


@dataclass
class Setup:
    """One data set prepared for fitting: the problem arrays, the parameter layout, the start
    θ0 (a dict of blocks), flat parameter `names` (stable keys) and `labels` (physical
    names for reports), the measured mask (N, 6) and the effects (all at their start
    values)."""

    problem: Problem
    layout: Layout
    theta0: dict
    names: list
    mask: np.ndarray
    effects: dict
    labels: list = field(default_factory=list)
    noise: NoiseModel | None = None
    prior: np.ndarray | None = None  # (P,) 1 / σ of the prior on each parameter (`prior.py`)

    def free_mask(self, free) -> np.ndarray:
        """(P,) 0/1 over the flat parameters: the blocks named in `free` plus the nuisance
        frame/target blocks (a frame drift, θ "frame_drift", only where `free` names it)."""
        keep = tuple(free) + ("frame", "target")
        out = []
        for key in sorted(self.theta0):
            on = key in keep
            out += [1.0 if on else 0.0] * int(np.asarray(self.theta0[key]).size)
        return np.asarray(out)


def setup(
    nominal: Table,
    data: Measurements,
    free=params.GEOMETRY,
    *,
    effects=None,
    compensated: bool | None = None,
    estimate_frame: bool = True,
    sigma: dict | None = None,
    column_ratio: dict | None = None,
    prior: Tolerances | None = None,
    frame_drift: bool = False,
) -> Setup:
    """Prepare `data` for fitting the `free` parameters of `nominal` + `effects` (see
    `calibrate`). Every block in `free` gets a θ entry (zero = the start value); with
    `frame_drift`, the instrument frame's DOFs get a drift over the file's time in each
    session too (θ "frame_drift", `Layout.frame_drift`). `sigma`:
    {column: σ (mm / rad)} stated by the user (overrides the file's σ columns);
    `column_ratio`: the noise groups' parts' σ ratios, fixed (`noise.noise_model`; default
    None: each fit tests one σ per group); `prior`: tolerances whose σ make a Gaussian
    prior on the geometry (`jaxtable._calibration.prior`; None: none)."""
    free = params.as_names(free)
    if frame_drift and not estimate_frame:
        raise ValueError("frame_drift: the instrument frame is not estimated (estimate_frame)")
    require_measured(data)
    check_units(data)
    check_angle_convention(data)
    ik = nominal_lengths(nominal, data)
    check_alignment(data, nominal, ik)
    mask = np.isfinite(data.measured)
    col_mask = mask.any(0)
    motion = np.ptp(data.cmd_pose[:, :3], axis=0)
    frame_dofs, target_dofs = nuisance_dofs(col_mask, motion) if estimate_frame else ((), ())
    gauge = []
    if len(frame_dofs) == 6 and "base_joints" in free:
        gauge.append("base_joints")
    if len(target_dofs) >= 3 and "platform_joints" in free:
        gauge.append("platform_joints")
    drift = bool(frame_drift and frame_dofs)
    layout = Layout(free, frame_dofs, target_dofs, len(data.sessions), tuple(gauge), drift)
    eff = resolve_effects(nominal, effects)
    bases = {
        n: (complement_basis(np.asarray(getattr(nominal, n))) if n in gauge else np.eye(18))
        for n in JOINTS
    }
    params.check(nominal, eff, free, allow_shared=True)
    noise = noise_model(
        data.measured,
        data.sigma,
        sigma,
        column_ratio,
        data.session_index,
        data.sessions,
        data.aside,
        data.relative_sigma,
    )
    problem = make_problem(
        nominal, data, eff, bases, compensated, used_columns(eff, free), noise.sigma0
    )
    check_commanded(data, nominal, ik)  # after the stroke check of `make_problem`: more specific
    theta0 = zero_steps(nominal, eff, free, bases)
    if frame_dofs:
        theta0["frame"] = device_array(initial_frames(data, frame_dofs)[:, list(frame_dofs)])
    if drift:
        theta0["frame_drift"] = device_array(np.zeros((len(data.sessions), len(frame_dofs))))
    if target_dofs:
        theta0["target"] = device_array(np.zeros(len(target_dofs)))
    keys, labels = parameter_keys(layout, theta0, bases)
    w = None if prior is None else prior_weights(keys, prior)
    return Setup(problem, layout, theta0, keys, mask, eff, labels, noise, w)


NOISE = ("estimate", "fixed")


@one_blas_thread
def fit(
    st: Setup,
    free_mask=None,
    rows=None,
    *,
    noise: str = "estimate",
    rtol: float = 1e-8,
    atol: float = 1e-8,
    max_steps: int = 200,
    identifiability_tol: float = 1e-6,
    theta0=None,
    method: str = "gauss_newton",
    weight=None,
) -> "Calibration":
    """Fit the parameters of `st` where `free_mask` (P,) is 1 (default: all), using only the
    data rows `rows` (bool (N,) or indices; default all: held-out rows get zero weight, so
    every fold and nested model of one data set reuses one compilation). `method`:
    "gauss_newton" (Gauss-Newton with truncated least-squares steps; default,
    falling back to LM when a step leaves the region where the forward kinematics converge)
    or "levenberg_marquardt" (optimistix LM: same optimum, several times more steps here).

    `noise`: "estimate" (default) refits with the σ of each noise group scaled until the
    residuals agree with them (variance-component estimation, `jaxtable._calibration.noise`;
    the stated σ, if any, only fix relative weights within a group, and the result says
    whether they agree with the data; a group's parts, its columns in each session, get
    their own scales where the data reject one, or keep the set-up's fixed ratios);
    "fixed": the weights as they are (the stated σ, or `weight` (N, 6) = 1/σ when given)."""
    if noise not in NOISE:
        raise ValueError(f"noise must be one of {NOISE}; got {noise!r}")
    base = np.asarray(st.problem.weight) if weight is None else np.asarray(weight, float)
    measured_rows = st.mask.any(axis=1)
    use = measured_rows.copy()
    if rows is not None:
        use = np.zeros(len(st.mask), bool)
        use[np.asarray(rows)] = True
        use &= measured_rows
    cells = st.mask & use[:, None]
    nm = st.noise or noise_model(np.where(st.mask, 0.0, np.nan), None)
    G = len(nm.names)
    kw = dict(
        rtol=rtol,
        atol=atol,
        max_steps=max_steps,
        identifiability_tol=identifiability_tol,
        method=method,
    )
    groups = np.asarray(nm.groups)
    # the scales are kept per part (column in a session) of each group (G, 6 S): one per
    # group unless the data reject that (`noise.pool_columns`), or in the noise model's
    # fixed ratios
    K = 6 * len(nm.sessions)
    by_column = column_groups(groups, nm.session, len(nm.sessions))
    # fixed ratios scale the σ the noise is estimated from ("fixed": weights as they are)
    fixed = nm.ratio is not None and noise == "estimate"
    column_scale = np.ones((G, K))
    for g, name in enumerate(nm.names):
        if fixed and name in nm.ratio and len(nm.ratio[name]) == K:
            column_scale[g] = np.asarray(nm.ratio[name], float)
    uneven = np.array([np.ptp(column_scale[g, nm.parts(g)]) > 0 for g in range(G)], bool)
    split = uneven.copy()
    p_min = np.full(G, np.inf)  # a split stays: it is reported with the p that made it
    start = theta0
    cal, red_g = None, np.zeros(G)
    iterations = 0
    for _ in range(8 if noise == "estimate" else 1):
        w = np.where(groups >= 0, base / column_scale.reshape(-1)[np.maximum(by_column, 0)], 0.0)
        cal = _fit_once(st, free_mask, use, w, theta0=start, **kw)
        iterations += 1
        red = cal.redundancy  # = noise.redundancy(cal.jacobian), without a second SVD
        s_col, red_col = group_scales(cal.residual, red, by_column, cells, n_groups=G * K)
        implied_col, red_col = (column_scale * s_col.reshape(G, K), red_col.reshape(G, K))
        # a group's scale while its columns share one: that one times what the group's
        # residuals imply (Σ e² / Σ r over all its cells)
        s_g, red_g = group_scales(cal.residual, red, groups, cells, n_groups=G)
        robust = column_scale * robust_scales(cal.residual, red, by_column, cells, G * K).reshape(
            G, K
        )
        if fixed:  # the ratios kept, the groups' scales estimated
            weights = column_scale * s_g[:, None]
            p_equal = equal_sigma_ps(robust, red_col)
            pooled = np.where(uneven, pooled_scales(implied_col, red_col), weights[:, 0])
        else:
            weights, pooled, split, p_equal = pool_columns(
                implied_col, red_col, split, column_scale[:, 0] * s_g, robust
            )
            p_min = np.fmin(p_min, p_equal)
            p_equal = np.where(split & ~uneven, p_min, p_equal)
        if noise != "estimate":
            break
        change = weights / column_scale
        column_scale = weights
        start = cal.theta  # warm start the refit
        if np.all(np.abs(change - 1.0) < 0.01):
            break
    # σ / σ0 the last fit's residuals imply (its weights hold it to 1 % when estimated)
    est = noise_estimate(
        nm, pooled, red_g, cells, noise == "estimate", implied_col, red_col, split, p_equal
    )
    cal.noise = dataclasses.replace(est, iterations=iterations)
    return cal


def _fit_once(
    st: Setup,
    free_mask,
    use: np.ndarray,
    weight: np.ndarray,
    *,
    rtol: float,
    atol: float,
    max_steps: int,
    identifiability_tol: float,
    theta0,
    method: str,
) -> "Calibration":
    """One weighted fit (see `fit`): rows where `use` is False and cells with weight 0 do not
    count; `weight` (N, 6) = 1/σ."""
    problem, layout = st.problem, st.layout
    problem = dataclasses.replace(problem, weight=device_array(weight))  # (as `_stop_blocks`)
    theta0 = st.theta0 if theta0 is None else theta0
    flat0 = _flat(theta0)
    fm = np.ones(flat0.shape[0]) if free_mask is None else np.asarray(free_mask, float)
    measured_rows = st.mask.any(axis=1)  # a row with nothing measured is skipped
    if not use.all():
        problem = dataclasses.replace(
            problem, weight=device_array(np.asarray(problem.weight) * use[:, None])
        )
    mask = st.mask & use[:, None]
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}; got {method!r}")
    args = (problem, layout, theta0, device_array(fm), rtol, atol, max_steps)
    value, converged, steps, J, solved, r0, r = _solve(*args, method, identifiability_tol, st.prior)
    if method == "gauss_newton" and not (bool(converged) and np.all(np.asarray(solved)[use])):
        # the trust region's Gauss-Newton ran out of steps (creeping along a curved valley
        # of barely determined directions, e.g. an x interferometer on a line): optimistix's
        # LM from the start, whose damping takes another path
        value, converged, steps, J, solved, r0, r = _solve(
            *args, "levenberg_marquardt", identifiability_tol, st.prior
        )
    if not np.all(np.asarray(solved)[use]):
        bad = np.flatnonzero(~np.asarray(solved) & use)
        raise KinematicsError(
            "the forward kinematics did not converge at the fitted parameters for row(s) "
            + ", ".join(str(b) for b in (bad + 1).tolist()[:10])
            + (", ..." if len(bad) > 10 else "")
            + " (numbered from 1, the first data row): the fit moved the table where those "
            "rows' commanded lengths have no pose near their commanded pose; check those rows"
        )
    before = np.asarray(r0).reshape(-1, 6)
    after = np.asarray(r).reshape(-1, 6)
    on = fm > 0
    J_full = np.asarray(J)
    J = J_full[:, on]
    flat = _flat(value)[on]
    names = [n for n, k in zip(st.names, on) if k]
    labels = [n for n, k in zip(st.labels or st.names, on) if k]
    # identifiability: SVD of the column-scaled Jacobian, below it the prior's
    # pseudo-observations (one row a parameter with a prior): the covariance is then the
    # posterior's, and the hat matrix's data rows give the data's redundancy
    w_prior = np.zeros(on.sum()) if st.prior is None else np.asarray(st.prior, float)[on]
    has_prior = w_prior > 0
    A = np.concatenate([J, np.diag(w_prior)[has_prior]])
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    U, sv, Vt = np.linalg.svd(A / scale, full_matrices=False)
    U = U[: J.shape[0]]  # the data's rows
    ok = sv > identifiability_tol * sv[0]
    unident = []
    for k in np.flatnonzero(~ok):
        v = Vt[k] / np.abs(Vt[k]).max()
        top = np.argsort(-np.abs(v))[:4]
        unident.append(
            (float(sv[k] / sv[0]), [(labels[i], float(v[i])) for i in top if abs(v[i]) > 0.05])
        )
    red = np.where(np.any(J != 0, axis=1), 1.0 - np.sum(U[:, ok] ** 2, axis=1), 0.0)
    inv_s2 = np.where(ok, 1.0 / np.where(ok, sv, 1.0) ** 2, 0.0)
    cov = (Vt.T * inv_s2) @ Vt / np.outer(scale, scale)
    std = np.sqrt(np.diag(cov))
    null_weight = (Vt[~ok] ** 2).sum(0)
    std = np.where(null_weight > 1e-6, np.inf, std)
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(np.sqrt(np.diag(cov)), np.sqrt(np.diag(cov)))
    table, effects_fit, frame, target, drift = build_model(problem, layout, value)
    prior_sigma = None
    if has_prior.any():
        prior_sigma = np.where(has_prior, 1.0 / np.where(has_prior, w_prior, 1.0), np.inf)
    cols = [c for k, c in enumerate(COLUMNS) if mask[:, k].any()]
    w_fit = np.asarray(problem.weight)
    on = mask & (w_fit > 0)  # a reading given zero weight (set aside) is not fitted
    sig = np.where(on, 1.0 / np.where(on, w_fit, 1.0), np.nan)

    def rms(res):
        r = res * sig  # back to physical units
        return {
            c: float(np.sqrt(np.nanmean(np.where(mask[:, k], r[:, k], np.nan) ** 2)))
            for k, c in enumerate(COLUMNS)
            if c in cols
        }

    n_obs = int(mask.sum())
    # the parameters the data determine: the rank, or with a prior the hat matrix's trace
    # over the data's rows (each direction counts by the share of its information the
    # data give, between 0 and 1)
    fitted = int(ok.sum()) if prior_sigma is None else int(round(float(np.sum(U[:, ok] ** 2))))
    return Calibration(
        table=table,
        effects=effects_fit,
        frame=np.asarray(frame),
        target=np.asarray(target),
        names=names,
        frame_drift=(
            np.asarray(drift) if any(n.startswith("frame_drift[") for n in names) else None
        ),
        session_time=_session_times(problem, measured_rows, layout.n_sessions),
        labels=labels,
        rms_sigma_before=sigma_rms(before, mask),
        rms_sigma_after=sigma_rms(after, mask),
        value=flat,
        std=std,
        correlation=corr,
        singular_values=sv / sv[0],
        unidentifiable=unident,
        rms_before=rms(before),
        rms_after=rms(after),
        chi2=float((after[use] ** 2).sum()),
        dof=n_obs - fitted,
        converged=bool(converged),
        rows_skipped=int((~measured_rows).sum()),
        weight=np.asarray(weight),
        steps=int(steps),
        layout=layout,
        bases=st.problem.bases,
        theta=value,
        effects_nominal=st.effects,
        rank=int(ok.sum()),
        n_obs=n_obs,
        residual=after,
        covariance=cov,
        jacobian=J,
        jacobian_full=J_full,
        redundancy=red,
        prior_sigma=prior_sigma,
        chi2_prior=float(np.sum((w_prior * flat) ** 2)),
    )


@one_blas_thread
def calibrate(
    nominal: Table,
    data: Measurements,
    free=params.GEOMETRY,
    *,
    effects=None,
    compensated: bool | None = None,
    estimate_frame: bool = True,
    sigma: dict | None = None,
    noise: str = "estimate",
    identifiability_tol: float = 1e-6,
    rtol: float = 1e-8,
    atol: float = 1e-8,
    max_steps: int = 200,
    method: str = "gauss_newton",
    outliers: str = "set_aside",
    prior: Tolerances | None = None,
    frame_drift: bool = False,
) -> "Calibration":
    """Fit the `free` parameters (table leaves: base_joints, platform_joints, zero_lengths,
    ...; effect fields: "spiral.lead", ...; a shared field as one number for all legs:
    "thermal.alpha[all]") of the model `nominal` + `effects` (default: its hardware
    effects) to `data`.

    A fit whose table is not physical (the fit moved directions the data barely determine
    until a home length left the stroke: `not_physical`) is returned with a RuntimeWarning
    saying why; the command line refuses it.

    Commanded lengths come from the data, or (absent) from the nominal inverse kinematics,
    compensated for the spiral term when `compensated` (which must then be stated when the
    table has a lead: `commanded_lengths`). With `estimate_frame`, the instrument
    frame of each session and the target offset are estimated (initialised in closed form)
    over the components the instrument can see, and the joint sets are fitted modulo rigid
    motions (the gauge). Directions whose scaled singular value is below
    `identifiability_tol` × the largest are reported as unidentifiable and get std = inf.
    `sigma`: {column: σ (mm / rad)} stated by the user (else the file's σ columns, if any);
    `noise`: "estimate" (default: the σ of each group of columns is estimated from the fit,
    and a stated σ is tested against it) or "fixed" (trust the stated σ); see `fit`.
    `outliers`: "set_aside" (default: readings the fit cannot reconcile with the rest are
    found by data snooping with a robust scale, set aside as not measured, and the model
    refitted; `Calibration.set_aside` names them; see `outliers`; rows that repeat an
    earlier row to the last digit are set aside before any fit, `Calibration.repeated`)
    or "keep". A stop read in several consecutive rows (one command) is fitted once, at the
    mean of its readings (`stops.merge_stops`; `Calibration.stops` reports the noise within
    stops and the table's repeatability; `Calibration.data` is the data as fitted).
    `prior`: a tolerance budget (`Tolerances`, e.g. `jt.Tolerances()` for the paper's, or
    `jt.load_tolerances(path)`): the table as built is the nominal one within it, a Gaussian
    prior on the joints, zero lengths, lead-scale error and spiral lead
    (`tolerances.parameter_sigma`). The fit is then the maximum a posteriori estimate, and
    `std` / `covariance` the posterior's: what the data cannot determine stays within its
    tolerance (σ = its prior σ) instead of drifting with σ = inf, and `prior_share` says
    how much of each parameter's prior variance the data left. Default None: no prior.
    `frame_drift`: the instrument's frame also drifts, linearly over the file's time in
    each session (a tracker or its stand warming up: every reading moves alike, where a
    drift of the legs would move the platform differently over the workspace), fitted as a
    nuisance beside the frame (`Calibration.frame_drift`); not part of the model.
    """
    cal = fit_screened(
        nominal,
        data,
        free,
        effects=effects,
        compensated=compensated,
        estimate_frame=estimate_frame,
        sigma=sigma,
        noise=noise,
        identifiability_tol=identifiability_tol,
        rtol=rtol,
        atol=atol,
        max_steps=max_steps,
        method=method,
        outliers=outliers,
        prior=prior,
        frame_drift=frame_drift,
    )[1]
    warn_not_physical(cal)
    return cal


def not_physical(cal: "Calibration") -> str | None:
    """Why a fit left a table that is not a hexapod the table file accepts (home lengths
    outside the stroke, ...), with what to do about it; None for a physical table. Such a
    fit moved directions the data barely determine: typically too many free parameters
    for the columns and stops measured."""
    try:
        check_table(cal.table)
    except TableFileError as e:
        problems = str(e).split("\n", 1)[-1].strip().replace("\n  ", "; ")
        return (
            f"the fitted table is not physical ({problems}): the fit "
            + ("did not converge" if not cal.converged else "converged")
            + f" in {cal.steps} steps and moved directions these data barely determine "
            f"({cal.n_obs} readings for {len(cal.value)} parameters, "
            f"{len(cal.unidentifiable)} combination(s) undetermined); fit fewer parameters "
            "(e.g. --free zero_lengths), or measure more columns or stops"
        )
    return None


def check_physical(cal: "Calibration") -> None:
    """Raise KinematicsError where the fitted table is not physical (`not_physical`): the
    command line's rule, before anything is written."""
    why = not_physical(cal)
    if why is not None:
        raise KinematicsError(why)


def warn_not_physical(cal: "Calibration") -> None:
    """The API's rule: a fit whose table is not physical is returned for inspection (its
    `unidentifiable` directions, `converged`), with a RuntimeWarning saying why; saving
    its table is refused (`TableFileError`)."""
    why = not_physical(cal)
    if why is not None:
        warnings.warn(
            why + "; the fit is returned for inspection, its table cannot be saved",
            RuntimeWarning,
            stacklevel=3,
        )


def _gross_errors(problem: "Problem", cal: "Calibration", cells: list) -> list:
    """`GrossError`s, largest first, of the readings `cells` ((row, column, z) as the screen
    finds them): measured − model of fit `cal` on `problem`'s readings."""
    if not cells:
        return []
    res = weighted_residual(problem, cal.layout, cal.theta)
    w = np.asarray(problem.weight)
    out = []
    for r, c, z in cells:
        value = -float(res[r, c] / w[r, c])
        value = value if c < 3 else float(np.rad2deg(value))
        out.append(GrossError(r + 1, POSE_COLUMNS[c], value, z))
    return sorted(out, key=lambda g: -abs(g.z))


def fit_screened(nominal: Table, data: Measurements, free, *, outliers="set_aside", **kw):
    """`calibrate` returning (set-up, fit): with outliers="set_aside" the set-up of the data
    with the gross errors set aside (`outliers.without`), which the fit was made on. `kw`:
    `setup`'s keywords (effects, compensated, estimate_frame, sigma) and `fit`'s."""
    if outliers not in OUTLIERS:
        raise ValueError(f"outliers must be one of {OUTLIERS}; got {outliers!r}")
    free = params.as_names(free)
    params.check_distinct(free)
    setup_kw = {
        k: kw.pop(k)
        for k in ("effects", "compensated", "estimate_frame", "sigma", "prior", "frame_drift")
        if k in kw
    }

    def run(d):
        st = setup(nominal, d, free, **setup_kw)
        return st, fit(st, **kw)

    if outliers == "keep":
        data, stops = merge_stops(data, screen=False)
        data, stops, st, cal = weighed_fit(data, stops, *run(data), run)
        cal.stops, cal.data = stops, data
        return st, cal
    # rows a logger wrote twice and readings no table could have produced (a tracker that
    # lost its target), before any fit: they would corrupt it, and the structure they leave
    # stops the screen; then a stop read several times fitted once, at its readings' mean
    data, repeated, pre = prescreen(data)
    data, stops = merge_stops(data)
    pre += [] if stops is None else stops.set_aside
    data, stops, st, cal = weighed_fit(data, stops, *run(data), run)
    st, cal = set_aside_gross_errors(data, st, cal, run, setup_kw.get("compensated"))
    cal.data = without(data, cal.set_aside)
    if pre:
        cal.set_aside = sorted(pre + list(cal.set_aside), key=lambda g: -abs(g.z))
    cal.repeated, cal.stops = repeated, stops
    return st, cal


OUTLIERS = ("set_aside", "keep")


def weighed_by(data: Measurements, stops, st: "Setup", cal: "Calibration"):
    """`stops.weigh_stops` of `data` with the noise groups of set-up `st` and the σ of its
    fit `cal` (which weighted the stops alike): (data, stops) with each stop's mean
    weighted by its readings, or None where the weights stay alike."""
    if stops is None or st.noise is None or cal.noise is None:
        return None
    return weigh_stops(data, stops, st.noise.groups, cal.noise.sigma, cal.noise.stated)


def weighed_fit(data: Measurements, stops, st: "Setup", cal: "Calibration", run):
    """(data, stops, set-up, fit): where the stops of `data` were read a different number
    of times, each stop's mean weighted by its readings (`weighed_by`) and the fit made
    again with `run(data) -> (setup, fit)`; the arguments as they are otherwise."""
    out = weighed_by(data, stops, st, cal)
    if out is None:
        return data, stops, st, cal
    data, stops = out
    return (data, stops, *run(data))


def set_aside_gross_errors(
    data: Measurements, st: "Setup", cal: "Calibration", run, compensated, rounds: int = 100
):
    """Screen fit `cal` of `data` (set-up `st`) for gross errors (`outliers.screen`); while
    one is found, set it aside (not measured) and refit with `run(data) -> (setup, fit)`.
    Returns the last (set-up, fit), the fit with `set_aside` (`GrossError`s, largest first,
    each with its residual from that fit) and `untested`.

    Data snooping needs a model that fits. Where the fit's residuals show structure
    (`structure_test`), the screen is tried for at most `TRIAL_ROUNDS` readings and kept
    only if the model refitted without them leaves none: a burst of gross errors (a tracker
    that lost its beam for three readings) makes structure that goes with them; an effect
    the model lacks does not, and then nothing is set aside."""
    from .._discovery.structure import TooFewRowsError, structure_test

    found = []
    untested = crowded = 0
    original, first = data, (st, cal)
    try:
        test = structure_test(cal, st)
    except TooFewRowsError as e:  # too few rows to test (or to screen)
        cal.set_aside, cal.screen_skipped = [], str(e)
        return st, cal
    if test.structure:
        rounds = min(rounds, TRIAL_ROUNDS)
    for _ in range(rounds):
        groups = np.asarray(st.noise.groups) if st.noise is not None else np.zeros((len(data), 6))
        new, _, untested, crowded = screen_gross_errors(
            cal,
            st.mask,
            screen_groups(groups, st.problem.session, st.layout.n_sessions, st.mask),
            st.problem.s,
            st.problem.session,
        )
        if new is None:
            break
        found.append(new)
        data = without(data, [new[:2]])
        st, cal = run(data)
    if test.structure and (not found or new is not None or structure_test(cal, st).structure):
        # structure the set-aside readings do not explain: none is a gross error to tell;
        # a step in time within a session may (the instrument or the legs' zeros moved):
        # named where the fit with the rows after it as a session of their own leaves none
        from .._discovery.changepoint import split_label, split_session, step_scan

        st, cal = first
        cal.set_aside, cal.screen_skipped = [], test.words()
        cal.suspects = _gross_errors(st.problem, cal, found)
        step = step_scan(cal, st)
        if step is not None and step.found:
            label = split_label(original, step)
            st2, cal2 = run(split_session(original, step.row - 1, label))
            if not structure_test(cal2, st2).structure:
                cal.step = step
        return st, cal
    if found:
        # measured − model of the readings set aside, from the final fit (not fitted there);
        # on every row, so that the sessions keep their frames
        problem = make_problem(
            st.problem.nominal, original, cal.effects_nominal, cal.bases, compensated
        )
        found = _gross_errors(problem, cal, found)
    cal.set_aside = found
    cal.untested = untested
    cal.crowded = crowded
    return st, cal
