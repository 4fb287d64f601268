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

from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree

from ._api import actuator_command
from ._context import Context, directions
from ._data import Measurements
from ._effects import resolve_effects
from ._forward import ForwardOptions, forward_one
from ._instrument import observe
from ._table import Table

JOINTS = ("base_joints", "platform_joints")
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


def _nuisance_dofs(measured_mask: np.ndarray):
    t = measured_mask[:3].sum()
    r = measured_mask[3:].sum()
    if t == 3:
        frame = (0, 1, 2, 3, 4, 5)
        target = (0, 1, 2, 3, 4, 5) if r == 3 else (0, 1, 2)
    else:
        frame = tuple(int(k) for k in np.flatnonzero(measured_mask[:3]))
        target = ()
    return frame, target


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


def _build(problem: Problem, layout: Layout, theta):
    table = problem.start
    changes = {}
    for name in layout.free:
        if name in JOINTS:
            d = problem.bases[name] @ theta[name]
            changes[name] = getattr(table, name) + d.reshape(6, 3)
        elif "." not in name:
            changes[name] = getattr(table, name) + theta[name]
    if changes:
        names = list(changes)
        table = eqx.tree_at(
            lambda t: [getattr(t, n) for n in names], table, [changes[n] for n in names]
        )
    effects = dict(problem.effects)
    for name in layout.free:
        if "." in name:
            eff, fld = name.split(".", 1)
            effects[eff] = eqx.tree_at(
                lambda e: getattr(e, fld), effects[eff], getattr(effects[eff], fld) + theta[name]
            )
    frame = (
        jnp.zeros((layout.n_sessions, 6)).at[:, np.array(layout.frame_dofs)].set(theta["frame"])
        if layout.frame_dofs
        else jnp.zeros((layout.n_sessions, 6))
    )
    target = (
        jnp.zeros(6).at[np.array(layout.target_dofs)].set(theta["target"])
        if layout.target_dofs
        else jnp.zeros(6)
    )
    return table, effects, frame, target


def _predict(problem: Problem, layout: Layout, theta, options=ForwardOptions()):
    table, effects, frame, target = _build(problem, layout, theta)

    def one(s, g, sess, ctx):
        q, code, _, _ = forward_one(table, effects, s, g, options, ctx)
        return observe(q, frame[sess], target), code

    return jax.vmap(one)(problem.s, problem.guess, problem.session, problem.ctx)


def _residual(theta, args):
    problem, layout = args
    reading, _ = _predict(problem, layout, theta)
    diff = reading - problem.measured
    diff = diff.at[:, 3:].set(jnp.mod(diff[:, 3:] + jnp.pi, 2 * jnp.pi) - jnp.pi)
    return (diff * problem.weight).reshape(-1)


_residual_jit = eqx.filter_jit(_residual)


@eqx.filter_jit
def _solve(problem, layout, theta0, mask, rtol, atol, max_steps, method="gauss_newton", rcond=1e-6):
    """Gauss-Newton in Jacobi-scaled variables u (θ = θ0 + D·mask·u, D = 1 / column norms of the
    Jacobian at θ0): mm, rad and mm/rev parameters then take comparable steps. `mask` (P,)
    (0/1, traced) freezes parameters without recompiling, so nested models and folds of one
    data set share one compilation."""
    flat0, unravel = ravel_pytree(theta0)

    def res_flat(f):
        return _residual(unravel(f), (problem, layout))

    J0 = jax.jacfwd(res_flat)(flat0)
    norms = jnp.linalg.norm(J0, axis=0)
    D = jnp.where(norms > 0, 1.0 / jnp.where(norms > 0, norms, 1.0), 1.0) * mask

    def res_scaled(u, _):
        return res_flat(flat0 + D * u)

    # Gauss-Newton with a truncated-SVD least-squares step: the problems are nearly linear
    # (µm-level corrections, frames initialised in closed form), so it converges in a few
    # steps where LM's trust region takes tens; singular values below rcond × the largest
    # (frozen, i.e. masked, and unidentifiable directions) get no step, so they stay at their
    # start values instead of drifting.
    if method == "gauss_newton":
        solver = optx.GaussNewton(rtol=rtol, atol=atol, linear_solver=lx.SVD(rcond=rcond))
    else:
        solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    sol = optx.least_squares(
        res_scaled, solver, jnp.zeros_like(flat0), None, max_steps=max_steps, throw=False
    )
    flat = flat0 + D * sol.value
    J = jax.jacfwd(res_flat)(flat)
    value = unravel(flat)
    _, codes = _predict(problem, layout, value)
    return value, sol.result._value, sol.stats["num_steps"], J, codes


def _kabsch(P, Q):
    """Rotation R and translation t minimising |R P + t − Q| over rows (P, Q (N, 3))."""
    pc, qc = P.mean(0), Q.mean(0)
    H = (P - pc).T @ (Q - qc)
    U, S, Vt = np.linalg.svd(H)
    if S[1] < 1e-9 * max(S[0], 1e-300):  # collinear points: no rotation information
        return np.eye(3), qc - pc
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1, 1, d]) @ U.T
    return R, qc - R @ pc


def initial_frames(data: Measurements, frame_dofs) -> np.ndarray:
    """Closed-form instrument frames (S, 6) per session: rigid registration of the measured
    positions against the commanded ones (6-D), or the mean offset per measured column."""
    from ._instrument import euler_zyx

    out = np.zeros((len(data.sessions), 6))
    idx = data.session_index
    for k in range(len(data.sessions)):
        rows = idx == k
        P = data.cmd_pose[rows, :3]
        Q = data.measured[rows, :3]
        if len(frame_dofs) == 6:
            R, t = _kabsch(P, Q)
            out[k, :3] = t
            out[k, 3:] = np.asarray(euler_zyx(jnp.asarray(R)))
        else:
            for c in frame_dofs:
                out[k, c] = np.nanmean(Q[:, c] - P[:, c])
    return out


@dataclass
class Calibration:
    """Result of `calibrate`. `table`, `effects`: the fitted model; `frame` (S, 6) instrument
    frames per session and `target` (6,) (mm / rad); `names` of the fitted parameters (joint
    sets appear as their non-rigid components `base_joints.g1..12`); `value`, `std` and
    `correlation` of them (std = inf for an unidentifiable direction); `singular_values` of the
    column-scaled weighted Jacobian; `unidentifiable`: list of (singular value, [(name,
    weight), ...]) for each direction the data cannot determine; `rms_before` / `rms_after`
    per measured column (mm / rad); `chi2`, `dof`; `converged`, `steps`."""

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

    def parameter(self, prefix: str):
        """(value, std) arrays of the fitted parameters whose name starts with `prefix`
        (e.g. "spiral.lead")."""
        idx = [i for i, n in enumerate(self.names) if n == prefix or n.startswith(prefix + "[")]
        return self.value[idx], self.std[idx]

    def report(self) -> str:
        lines = [
            f"converged: {self.converged} ({self.steps} steps); chi2/dof = "
            f"{self.chi2:.1f}/{self.dof} = {self.chi2 / max(self.dof, 1):.3f}",
            "RMS residual per measured column (before -> after): "
            + ", ".join(
                f"{c} {self.rms_before[c]:.4g} -> {self.rms_after[c]:.4g}" for c in self.rms_after
            ),
        ]
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
                    f"  - (singular value {sv:.1e}) " + " ".join(f"{w:+.2f}*{n}" for n, w in parts)
                )
            if len(self.unidentifiable) > 12:
                lines.append(f"  ... and {len(self.unidentifiable) - 12} more")
        else:
            lines.append("every fitted parameter is identifiable from these data")
        return "\n".join(lines)


def _names(layout: Layout, theta0) -> list:
    out = []
    for key in sorted(theta0):  # ravel_pytree flattens dict keys in sorted order
        v = np.asarray(theta0[key])
        if key in JOINTS:
            out += [f"{key}.g{i + 1}" for i in range(v.size)]
        elif key == "frame":
            labels = "x y z roll pitch yaw".split()
            out += [
                f"frame[{s + 1}].{labels[d]}" for s in range(v.shape[0]) for d in layout.frame_dofs
            ]
        elif key == "target":
            labels = "x y z roll pitch yaw".split()
            out += [f"target.{labels[d]}" for d in layout.target_dofs]
        elif v.ndim == 0:
            out.append(key)
        else:
            out += [f"{key}[{i + 1}]" for i in range(v.size)]
    return out


def data_context(data: Measurements, cmd: np.ndarray) -> Context:
    """Batched context (N,) of the data's stops: direction of travel from the row order of
    the commanded lengths `cmd` (N, 6), temperature (20 °C if absent), payload (0 if absent),
    session index."""
    n = len(data)
    return Context(
        directions(cmd),
        np.full(n, 20.0) if data.temperature is None else np.asarray(data.temperature, float),
        np.zeros(n) if data.payload is None else np.asarray(data.payload, float),
        np.asarray(data.session_index),
    )


def make_problem(nominal: Table, data: Measurements, effects, bases, compensated=True):
    """Arrays of a calibration problem; refuses commands outside the stroke (row, leg named)
    and measured values without a positive σ."""
    mask = np.isfinite(data.measured)
    cmd = (
        data.cmd_lengths
        if data.cmd_lengths is not None
        else np.asarray(
            actuator_command(nominal, data.cmd_pose, compensate=compensated, check=False)
        )
    )
    lo, hi = (float(v) for v in np.asarray(nominal.stroke))
    bad = np.argwhere((cmd < lo) | (cmd > hi) | ~np.isfinite(cmd))
    if len(bad):
        r, leg = bad[0]
        raise ValueError(
            f"row {r + 1}: commanded length of leg {leg + 1} ({cmd[r, leg]:.3f} mm) is outside "
            f"the stroke [{lo}, {hi}]" + (f" ({len(bad)} such cells)" if len(bad) > 1 else "")
        )
    sigma = data.sigma if data.sigma is not None else np.full(data.measured.shape, np.nan)
    bad = np.argwhere(mask & ~(sigma > 0))
    if len(bad):
        r, c = bad[0]
        raise ValueError(
            f"row {r + 1}, column '{'x y z roll pitch yaw'.split()[c]}': measured "
            f"value without a positive σ (sigma_ column)"
        )
    return Problem(
        nominal=nominal,
        start=nominal,
        effects=effects,
        s=jnp.asarray(cmd - np.asarray(nominal.zero_lengths)),
        guess=jnp.asarray(data.cmd_pose),
        measured=jnp.asarray(np.where(mask, data.measured, 0.0)),
        weight=jnp.asarray(np.where(mask, 1.0 / np.where(mask, sigma, 1.0), 0.0)),
        session=jnp.asarray(data.session_index),
        bases={n: jnp.asarray(b) for n, b in bases.items()},
        ctx=data_context(data, cmd),
    )


def validate(cal: "Calibration", nominal: Table, data: Measurements, compensated=True) -> dict:
    """RMS residual per measured column (mm / rad) of the calibrated model on `data` (e.g.
    held-out poses), in the calibration's instrument frames (sessions matched by order of
    first appearance)."""
    problem = make_problem(nominal, data, cal.effects_nominal, cal.bases, compensated)
    res = np.asarray(_residual_jit(cal.theta, (problem, cal.layout))).reshape(-1, 6)
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
    θ0 (a dict of blocks), flat parameter `names`, the measured mask (N, 6) and the effects
    (all at their start values)."""

    problem: Problem
    layout: Layout
    theta0: dict
    names: list
    mask: np.ndarray
    effects: dict

    def free_mask(self, free) -> np.ndarray:
        """(P,) 0/1 over the flat parameters: the blocks named in `free` plus the nuisance
        frame/target blocks."""
        keep = tuple(free) + ("frame", "target")
        out = []
        for key in sorted(self.theta0):
            on = key in keep
            out += [1.0 if on else 0.0] * int(np.asarray(self.theta0[key]).size)
        return np.asarray(out)


def setup(
    nominal: Table,
    data: Measurements,
    free=("base_joints", "platform_joints", "zero_lengths"),
    *,
    effects=None,
    compensated: bool = True,
    estimate_frame: bool = True,
) -> Setup:
    """Prepare `data` for fitting the `free` parameters of `nominal` + `effects` (see
    `calibrate`). Every block in `free` gets a θ entry (zero = the start value)."""
    free = tuple(free)
    if not np.isfinite(data.measured).any():
        raise ValueError("no measured values in the data")
    mask = np.isfinite(data.measured)
    col_mask = mask.any(0)
    frame_dofs, target_dofs = _nuisance_dofs(col_mask) if estimate_frame else ((), ())
    gauge = []
    if len(frame_dofs) == 6 and "base_joints" in free:
        gauge.append("base_joints")
    if len(target_dofs) >= 3 and "platform_joints" in free:
        gauge.append("platform_joints")
    layout = Layout(free, frame_dofs, target_dofs, len(data.sessions), tuple(gauge))
    eff = resolve_effects(nominal, effects)
    bases = {
        n: (complement_basis(np.asarray(getattr(nominal, n))) if n in gauge else np.eye(18))
        for n in JOINTS
    }
    problem = make_problem(nominal, data, eff, bases, compensated)
    theta0 = {}
    for name in free:
        if name in JOINTS:
            theta0[name] = jnp.zeros(bases[name].shape[1])
        elif "." in name:
            e, f = name.split(".", 1)
            if e not in eff:
                raise ValueError(f"free parameter '{name}': no effect '{e}' in the model")
            theta0[name] = jnp.zeros_like(getattr(eff[e], f))
        else:
            if not hasattr(nominal, name):
                raise ValueError(f"free parameter '{name}': the table has no such leaf")
            theta0[name] = jnp.zeros_like(getattr(nominal, name))
    if frame_dofs:
        theta0["frame"] = jnp.asarray(initial_frames(data, frame_dofs)[:, list(frame_dofs)])
    if target_dofs:
        theta0["target"] = jnp.zeros(len(target_dofs))
    return Setup(problem, layout, theta0, _names(layout, theta0), mask, eff)


def fit(
    st: Setup,
    free_mask=None,
    rows=None,
    *,
    rtol: float = 1e-8,
    atol: float = 1e-8,
    max_steps: int = 200,
    identifiability_tol: float = 1e-6,
    theta0=None,
    method: str = "gauss_newton",
) -> "Calibration":
    """Fit the parameters of `st` where `free_mask` (P,) is 1 (default: all), using only the
    data rows `rows` (bool (N,) or indices; default all: held-out rows get zero weight, so
    every fold and nested model of one data set reuses one compilation). `method`:
    "gauss_newton" (optimistix GaussNewton, truncated-SVD least-squares steps; default,
    falling back to LM when a step leaves the region where the forward kinematics converge)
    or "levenberg_marquardt" (optimistix LM: same optimum, several times more steps here)."""
    problem, layout = st.problem, st.layout
    theta0 = st.theta0 if theta0 is None else theta0
    flat0, _ = ravel_pytree(theta0)
    fm = np.ones(flat0.shape[0]) if free_mask is None else np.asarray(free_mask, float)
    use = np.ones(len(st.mask), bool)
    if rows is not None:
        use = np.zeros(len(st.mask), bool)
        use[np.asarray(rows)] = True
    if not use.all():
        problem = eqx.tree_at(
            lambda p: p.weight, problem, problem.weight * jnp.asarray(use, float)[:, None]
        )
    mask = st.mask & use[:, None]
    before = np.asarray(_residual_jit(theta0, (problem, layout))).reshape(-1, 6)
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}; got {method!r}")
    args = (problem, layout, theta0, jnp.asarray(fm), rtol, atol, max_steps)
    value, code, steps, J, codes = _solve(*args, method, identifiability_tol)
    if method == "gauss_newton" and (int(code) != 0 or np.any(np.asarray(codes)[use] != 0)):
        # undamped steps along weakly determined directions left the region where the
        # forward kinematics converge (e.g. an x-only instrument on a line): LM's damping
        # keeps them bounded
        value, code, steps, J, codes = _solve(*args, "levenberg_marquardt", identifiability_tol)
    if np.any(np.asarray(codes)[use] != 0):
        bad = np.flatnonzero((np.asarray(codes) != 0) & use)
        raise RuntimeError(
            f"forward kinematics failed at the fitted parameters for row(s) "
            f"{(bad + 1).tolist()[:10]}"
        )
    after = np.asarray(_residual_jit(value, (problem, layout))).reshape(-1, 6)
    on = fm > 0
    J = np.asarray(J)[:, on]
    flat = np.asarray(ravel_pytree(value)[0])[on]
    names = [n for n, k in zip(st.names, on) if k]
    # identifiability: SVD of the column-scaled Jacobian
    scale = np.linalg.norm(J, axis=0)
    scale[scale == 0] = 1.0
    U, sv, Vt = np.linalg.svd(J / scale, full_matrices=False)
    ok = sv > identifiability_tol * sv[0]
    unident = []
    for k in np.flatnonzero(~ok):
        v = Vt[k] / np.abs(Vt[k]).max()
        top = np.argsort(-np.abs(v))[:4]
        unident.append(
            (float(sv[k] / sv[0]), [(names[i], float(v[i])) for i in top if abs(v[i]) > 0.05])
        )
    inv_s2 = np.where(ok, 1.0 / np.where(ok, sv, 1.0) ** 2, 0.0)
    cov = (Vt.T * inv_s2) @ Vt / np.outer(scale, scale)
    std = np.sqrt(np.diag(cov))
    null_weight = (Vt[~ok] ** 2).sum(0)
    std = np.where(null_weight > 1e-6, np.inf, std)
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(np.sqrt(np.diag(cov)), np.sqrt(np.diag(cov)))
    table, effects_fit, frame, target = _build(problem, layout, value)
    cols = [c for k, c in enumerate(COLUMNS) if mask[:, k].any()]
    sig = np.where(mask, 1.0 / np.where(mask, np.asarray(problem.weight), 1.0), np.nan)

    def rms(res):
        r = res * sig  # back to physical units
        return {
            c: float(np.sqrt(np.nanmean(np.where(mask[:, k], r[:, k], np.nan) ** 2)))
            for k, c in enumerate(COLUMNS)
            if c in cols
        }

    n_obs = int(mask.sum())
    return Calibration(
        table=table,
        effects=effects_fit,
        frame=np.asarray(frame),
        target=np.asarray(target),
        names=names,
        value=flat,
        std=std,
        correlation=corr,
        singular_values=sv / sv[0],
        unidentifiable=unident,
        rms_before=rms(before),
        rms_after=rms(after),
        chi2=float((after[use] ** 2).sum()),
        dof=n_obs - int(ok.sum()),
        converged=int(code) == 0,
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
    )


def calibrate(
    nominal: Table,
    data: Measurements,
    free=("base_joints", "platform_joints", "zero_lengths"),
    *,
    effects=None,
    compensated: bool = True,
    estimate_frame: bool = True,
    identifiability_tol: float = 1e-6,
    rtol: float = 1e-8,
    atol: float = 1e-8,
    max_steps: int = 200,
    method: str = "gauss_newton",
) -> "Calibration":
    """Fit the `free` parameters (table leaves: base_joints, platform_joints, zero_lengths,
    ...; effect fields: "spiral.lead", ...) of the model `nominal` + `effects` (default: its
    hardware effects) to `data`.

    Commanded lengths come from the data, or (absent) from the nominal inverse kinematics,
    compensated for the spiral term when `compensated`. With `estimate_frame`, the instrument
    frame of each session and the target offset are estimated (initialised in closed form)
    over the components the instrument can see, and the joint sets are fitted modulo rigid
    motions (the gauge). Directions whose scaled singular value is below
    `identifiability_tol` × the largest are reported as unidentifiable and get std = inf.
    """
    st = setup(
        nominal,
        data,
        free,
        effects=effects,
        compensated=compensated,
        estimate_frame=estimate_frame,
    )
    return fit(
        st,
        identifiability_tol=identifiability_tol,
        rtol=rtol,
        atol=atol,
        max_steps=max_steps,
        method=method,
    )
