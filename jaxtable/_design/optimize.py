"""Design optimisation: continuous variables by gradient (optimistix BFGS on the smoothed
criteria, several starts), discrete ones by enumeration, constraints by a penalty that grows
over rounds, and the Pareto front between two criteria by the ε-constraint method.

Each continuous variable v lives in its bounds [lo, hi] through v = lo + (hi − lo)·σ(z), so
the optimiser works on an unbounded z and never leaves the bounds. The loss is

    ± f(v) / |f(v0)|  +  μ Σ_j max(0, (g_j(v) − V_j) / |V_j|)²       (μ = 10, 10³, 10⁵, 10⁷)

with f the objective (sign: − for criteria where more is better) and g_j ≤ V_j (or ≥) the
constraints, all smoothed (see `criteria`) with an exponent that grows over the rounds (p, p,
4p, 16p: the smoothed worst cases err on the safe side by at most n^(1/p), so the last round
lands within ~1 % of a binding limit). Every start, discrete choice and ε is one row of
one vmapped solve. The winner is chosen on the EXACT criteria over the full pose set: the best
objective among the candidates that meet every constraint (else the least violation).
"""

import itertools
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import ArrayLike, Float

from .._jit import jit
from .._threads import one_blas_thread
from .criteria import CRITERIA, criteria
from .evaluate import Assessment, assess, assess_batch, design_poses
from .variables import (
    DISCRETE,
    Design,
    check_design,
    default_bounds,
    get,
    set_values,
    stack,
    to_file_units,
)

ROUNDS = ((1e1, 1.0), (1e3, 1.0), (1e5, 4.0), (1e7, 16.0))
"""(penalty weight μ, factor on the smoothing exponent p) of each round: the penalty grows and
the worst cases sharpen, so the last round's safety margin n^(1/p) is small."""
FORWARD_UP_TO = 8
"""Up to this many continuous variables the loss's gradient is taken in forward mode (cost
~ one criteria evaluation per variable), beyond it in reverse mode (~ three, whatever the
number): see `gradient_mode`."""
FEASIBLE = 1e-6  # relative violation below which a constraint counts as met
HANDS = np.array(list(itertools.product([1.0, -1.0], repeat=6)))


@dataclass(frozen=True)
class Constraint:
    """`name` `op` `limit`: op '<=' or '>='; limit in the criterion's unit."""

    name: str
    op: str
    limit: float

    def violation(self, value):
        """Relative violation (> 0 when broken)."""
        return _relative_violation(self.op, self.limit, value)

    def __str__(self):
        return f"{self.name}{self.op}{self.limit:g}"


def _relative_violation(op: str, limit, value):
    """(value − limit) / |limit| for '<=', (limit − value) / |limit| for '>=' (|limit| taken
    as 1 for a zero limit); `limit` and `value` numbers or arrays, traced or not."""
    d = value - limit if op == "<=" else limit - value
    return d / (abs(limit) + (limit == 0))


def parse_constraint(text: str) -> Constraint:
    """'max_leg_force_N<=2000' or 'coverage>=1' -> Constraint (name checked)."""
    m = re.fullmatch(r"\s*([A-Za-z_]\w*)\s*(<=|>=)\s*([-+0-9.eE]+)\s*", text)
    if not m:
        raise ValueError(f"constraint '{text}': write NAME<=VALUE or NAME>=VALUE")
    name, op, value = m.groups()
    check_criterion(name, "constraint")
    try:
        return Constraint(name, op, float(value))
    except ValueError:
        raise ValueError(f"constraint '{text}': '{value}' is not a number") from None


def check_criterion(name: str, what: str = "objective") -> None:
    if name not in CRITERIA:
        raise ValueError(f"{what} '{name}' is not a criterion; use one of {', '.join(CRITERIA)}")


@dataclass
class DesignOptimum:
    """Result of `optimize_design`. `variables`: {name: (start, optimum)} in file units (deg
    for angles); `constraints`: [{name, op, limit, value, met}] at the optimum (exact);
    `candidates`: exact objective of every start/discrete choice (NaN-free), `feasible`: the
    optimum meets every constraint."""

    objective: str
    start: Assessment
    optimum: Assessment
    variables: dict
    constraints: list
    candidates: np.ndarray
    feasible: bool

    @property
    def start_value(self) -> float:
        return self.start.values[self.objective]

    @property
    def value(self) -> float:
        return self.optimum.values[self.objective]

    @property
    def design(self) -> Design:
        return self.optimum.design

    def as_json(self) -> dict:
        return {
            "objective": self.objective,
            "sense": CRITERIA[self.objective].sense,
            "start_value": self.start_value,
            "value": self.value,
            "design": {k: _jsonable(v[1]) for k, v in self.variables.items()},
            "start_design": {k: _jsonable(v[0]) for k, v in self.variables.items()},
            "constraints": self.constraints,
            "feasible": self.feasible,
            "start_criteria": self.start.values,
            "criteria": self.optimum.values,
        }


def _jsonable(v):
    return v.tolist() if isinstance(v, np.ndarray) else v


def _say(progress, text):
    if progress:
        print(text, file=sys.stderr, flush=True)


def _bounds(design, names, bounds):
    bounds = dict(bounds or {})
    out = {}
    for n in names:
        v0 = np.asarray(get(design, n))
        lo, hi = default_bounds(n, v0)
        if n in bounds:
            lo = np.broadcast_to(np.asarray(bounds[n][0], dtype=float), v0.shape)
            hi = np.broadcast_to(np.asarray(bounds[n][1], dtype=float), v0.shape)
        if np.any(lo >= hi):
            raise ValueError(f"bounds of '{n}': lower {lo.tolist()} not below upper {hi.tolist()}")
        if np.any((v0 < lo) | (v0 > hi)):
            raise ValueError(f"start value of '{n}' ({v0.tolist()}) is outside its bounds")
        out[n] = (lo, hi)
    return out


def _candidates(design, vary, lead_catalogue):
    """The discrete choices: designs (list) and a label for each."""
    choices = [[({}, "")]]
    if "hand" in vary:
        choices.append(
            [({"hand": h}, "hand " + "".join("R" if x > 0 else "L" for x in h)) for h in HANDS]
        )
    if "lead" in vary and lead_catalogue is not None:
        choices.append([({"lead": float(v)}, f"lead {v:g}") for v in lead_catalogue])
    designs, labels = [], []
    for combo in itertools.product(*choices):
        vals, lab = {}, []
        for v, label in combo:
            vals.update(v)
            lab.append(label)
        designs.append(set_values(design, vals) if vals else design)
        labels.append(", ".join(x for x in lab if x))
    return designs, labels


class _Loss(eqx.Module):
    """The penalised loss of `optimize_design` (module docstring) as a pytree: its numbers
    are arrays and its structure static, so every optimisation of the same variables,
    objective and kinds of constraint runs one compiled program, whatever the design,
    bounds, limits and poses."""

    lo: Float[ArrayLike, " V"]  # lower bounds of the flattened continuous variables
    hi: Float[ArrayLike, " V"]
    poses: Float[ArrayLike, "Q 6"]  # the reduced pose set the criteria are smoothed over
    limits: Float[ArrayLike, " C"]  # constraint limits
    sign: Float[ArrayLike, ""]  # −1 where more is better
    f_scale: Float[ArrayLike, ""]  # |objective at the start|
    names: tuple = eqx.field(static=True)  # the continuous variables
    shapes: tuple = eqx.field(static=True)  # their shapes
    objective: str = eqx.field(static=True)
    kinds: tuple = eqx.field(static=True)  # (criterion, op) of each constraint
    epsilon: tuple | None = eqx.field(static=True)  # (criterion, op) of the ε-constraint

    def values(self, z):
        """{variable: value} at the unbounded z (V,): numpy for numpy z, else jax."""
        xp = np if isinstance(z, np.ndarray) else jnp
        lo, hi = (xp.asarray(x) for x in (self.lo, self.hi))
        v = lo + (hi - lo) / (1.0 + xp.exp(-z))  # the logistic sigmoid
        sizes = [int(np.prod(s)) for s in self.shapes]
        parts = xp.split(v, np.cumsum(sizes)[:-1])
        return {n: p.reshape(s) for n, p, s in zip(self.names, parts, self.shapes)}

    def __call__(self, z, args):
        mu, p, d, eps = args
        d = set_values(d, self.values(z))  # geometry and hardware (lead, tolerances, ...)
        c = _criteria_once(d.table(), d.hardware, self.poses, p)
        pen = sum(
            jnp.maximum(0.0, _relative_violation(op, lim, c[name])) ** 2
            for (name, op), lim in zip(self.kinds, self.limits)
        )
        if self.epsilon is not None:
            name, op = self.epsilon
            pen = pen + jnp.maximum(0.0, _eps_violation(op, c[name], eps)) ** 2
        return self.sign * c[self.objective] / self.f_scale + mu * pen


# `criteria` as a nested jit: its ~7,600-equation program is traced once, then reused by
# each of the several traces BFGS makes of the loss and its gradient (jit caches the traced
# program and its derivative by argument types)
_criteria_once = jax.jit(criteria)


@jit
def _round(loss: _Loss, z, mu, p, args, mode: str):
    """One penalty round: BFGS on `loss` from every row of z (vmapped with the rows of
    `args`); `mu` and `p` traced, so every round runs one program. `mode`: optimistix's
    `autodiff_mode` for the loss's gradient, "fwd" or "bwd" (`gradient_mode`)."""
    solver = optx.BFGS(rtol=1e-6, atol=1e-8)

    def one(z, a):
        sol = optx.minimise(
            loss,
            solver,
            z,
            args=(mu, p, *a),
            max_steps=200,
            throw=False,
            options={"autodiff_mode": mode},
        )
        return sol.value

    return jax.vmap(one)(z, args)


def gradient_mode(n_variables: int) -> str:
    """How the loss's gradient is taken: forward mode ("fwd") up to `FORWARD_UP_TO`
    continuous variables, one tangent per variable through the criteria and no transposed
    program (a two-variable optimisation with and without a constraint: XLA compile 33 ->
    22-26 s); reverse mode ("bwd") beyond, whose cost does not grow with the number."""
    return "fwd" if n_variables <= FORWARD_UP_TO else "bwd"


def _solve_batch(loss: _Loss, z0, args, smooth, progress=False):
    """Minimise `loss(z, (mu, p, *args))` for every row of z0 / args (vmapped), over ROUNDS,
    warm-started."""
    z = z0
    for k, (mu, factor) in enumerate(ROUNDS):
        z = _round(
            loss, z, np.float64(mu), np.float64(smooth * factor), args, gradient_mode(z.shape[-1])
        )
        _say(progress, f"  penalty round {k + 1}/{len(ROUNDS)} done")
    return z


@one_blas_thread
def optimize_design(
    design: Design,
    vary: list[str],
    objective: str,
    constraints: Sequence[Constraint] = (),
    *,
    workspace=None,
    bounds: dict | None = None,
    lead_catalogue=None,
    starts: int = 4,
    seed: int = 0,
    smooth: float = 64.0,
    n_sweep: int = 7,
    n_random: int = 64,
    progress: bool = False,
    epsilon: tuple | None = None,
) -> DesignOptimum | list[tuple[Design, dict, bool]]:
    """Optimise `objective` (a CRITERIA key; its sense says min or max) over the variables
    `vary` of `design`, subject to `constraints`.

    Continuous variables follow the gradient of the smoothed criteria over a reduced pose set
    (`n_sweep` per DOF, `n_random` box poses), from the start and `starts − 1` random points
    in `bounds` ({name: (lo, hi)} internal units; default `default_bounds`). `hand` is
    enumerated over its 2⁶ choices and `lead` over `lead_catalogue` when one is given (one
    lead for all legs). Candidates are compared on the exact criteria over the full pose set
    (`assess` defaults). `epsilon` = (criterion, op, values) adds one ε-constraint per value
    (the Pareto front: see `pareto_front`); it then returns, per value, (design, exact
    criteria, feasible) instead of a DesignOptimum."""
    check_criterion(objective)
    vary = list(dict.fromkeys(vary))
    if not vary:
        raise ValueError("nothing to vary: name at least one design variable")
    check_design(design)
    for n in vary:
        get(design, n)  # names checked here
    discrete = [n for n in vary if n == "hand" or (n == "lead" and lead_catalogue is not None)]
    cont = [n for n in vary if n not in discrete]
    if lead_catalogue is not None and "lead" not in vary:
        raise ValueError("a lead catalogue was given but 'lead' is not varied")
    assert set(discrete) <= set(DISCRETE)

    start = assess(design, workspace=workspace)
    full_poses = start.poses
    opt_poses = jnp.asarray(design_poses(workspace, n_sweep, n_random, seed, box=2))
    sign = -1.0 if CRITERIA[objective].sense == "max" else 1.0
    f_scale = abs(start.values[objective]) or 1.0
    cons = list(constraints)

    designs, labels = _candidates(design, vary, lead_catalogue)
    eps_values = [None] if epsilon is None else list(epsilon[2])
    if cont:
        bnd = _bounds(design, cont, bounds)
        shapes = [np.shape(bnd[n][0]) for n in cont]
        lo = np.concatenate([np.ravel(bnd[n][0]) for n in cont])
        hi = np.concatenate([np.ravel(bnd[n][1]) for n in cont])

        loss = _Loss(
            lo,
            hi,
            opt_poses,
            np.asarray([k.limit for k in cons], float),
            np.float64(sign),
            np.float64(f_scale),
            tuple(cont),
            tuple(shapes),
            objective,
            tuple((k.name, k.op) for k in cons),
            None if epsilon is None else (epsilon[0], epsilon[1]),
        )
        v0 = np.concatenate([np.ravel(np.asarray(get(design, n))) for n in cont])
        u0 = (v0 - lo) / (hi - lo)
        rng = np.random.default_rng(seed)
        us = np.concatenate([u0[None], rng.uniform(0.02, 0.98, (starts - 1, len(v0)))])
        us = np.clip(us, 1e-6, 1 - 1e-6)
        z_starts = np.log(us) - np.log1p(-us)
        rows = list(itertools.product(range(len(designs)), range(len(eps_values)), range(starts)))
        Z0 = jnp.asarray(np.stack([z_starts[s] for _, _, s in rows]))
        D = stack([designs[i] for i, _, _ in rows])
        E = jnp.asarray([0.0 if eps_values[e] is None else eps_values[e] for _, e, _ in rows])
        _say(
            progress,
            f"optimising {objective} over {', '.join(cont)}: {len(rows)} solves "
            f"({starts} starts x {len(designs)} discrete choices x {len(eps_values)} ε) on "
            f"{len(opt_poses)} poses (compiling first) ...",
        )
        Z = np.asarray(_solve_batch(loss, Z0, (D, E), smooth, progress))
        finals = [set_values(designs[i], loss.values(z)) for (i, _, _), z in zip(rows, Z)]
    else:
        rows = [(i, 0, 0) for i in range(len(designs))]
        finals = designs
        _say(progress, f"enumerating {len(finals)} discrete designs ({', '.join(discrete)}) ...")

    exact = assess_batch(stack(finals), full_poses)
    # constraints and ε on the exact criteria
    viol = np.zeros(len(finals))
    for k in cons:
        viol += np.maximum(0.0, k.violation(exact[k.name]))
    results = []
    for e in range(len(eps_values)):
        idx = [r for r, row in enumerate(rows) if row[1] == e]
        v = viol[idx].copy()
        if epsilon is not None:
            v += np.maximum(0.0, _eps_violation(epsilon[1], exact[epsilon[0]][idx], eps_values[e]))
        obj = sign * exact[objective][idx]
        ok = v <= FEASIBLE
        pick = (
            idx[int(np.argmin(np.where(ok, obj, np.inf)))] if ok.any() else idx[int(np.argmin(v))]
        )
        results.append((pick, bool(ok.any())))
    if epsilon is not None:
        return [(finals[p], {k: float(exact[k][p]) for k in exact}, feas) for p, feas in results]

    pick, feasible = results[0]
    best = assess(finals[pick], workspace=workspace)
    variables = {
        n: (to_file_units(n, get(design, n)), to_file_units(n, get(best.design, n))) for n in vary
    }
    report = [
        {
            "name": k.name,
            "op": k.op,
            "limit": k.limit,
            "value": best.values[k.name],
            "met": bool(k.violation(best.values[k.name]) <= FEASIBLE),
        }
        for k in cons
    ]
    _say(progress, f"{objective}: {start.values[objective]:.6g} -> {best.values[objective]:.6g}")
    return DesignOptimum(
        objective,
        start,
        best,
        variables,
        report,
        exact[objective],
        feasible and all(r["met"] for r in report),
    )


def _eps_violation(op, value, eps):
    """Relative violation of the ε-constraint `value op eps` (> 0 when broken)."""
    d = value - eps if op == "<=" else eps - value
    return d / (abs(eps) + 1e-12)


@dataclass
class ParetoFront:
    """The trade-off between `objective` and `second`: `points` (list of dicts: the ε bound,
    both criteria, every varied variable in file units, feasible), non-dominated first."""

    objective: str
    second: str
    points: list
    ends: tuple  # (DesignOptimum for objective, DesignOptimum for second)

    def to_csv(self, path) -> None:
        keys = list(self.points[0]) if self.points else []
        lines = [",".join(keys)]
        for p in self.points:
            lines.append(",".join(_csv_cell(p[k]) for k in keys))
        from pathlib import Path

        Path(path).write_text("\n".join(lines) + "\n")


def _csv_cell(v):
    if isinstance(v, (list, np.ndarray)):
        return '"' + " ".join(f"{x:.10g}" for x in np.ravel(v)) + '"'
    if isinstance(v, bool):
        return str(v).lower()
    return f"{v:.10g}" if isinstance(v, float) else str(v)


@one_blas_thread
def pareto_front(
    design: Design,
    vary: list[str],
    objective: str,
    second: str,
    constraints: Sequence[Constraint] = (),
    *,
    n_points: int = 7,
    progress: bool = False,
    **options,
) -> ParetoFront:
    """The Pareto front between two criteria by the ε-constraint method: optimise `objective`
    alone and `second` alone (the ends), then `objective` with `second` bounded by each of
    `n_points` values ε spread between the ends (all ε in one vmapped solve). Points that
    another point beats on both criteria are dropped. `options`: as `optimize_design`."""
    check_criterion(objective)
    check_criterion(second, "second objective")
    if second == objective:
        raise ValueError("the two objectives of a Pareto front must differ")
    a = optimize_design(design, vary, objective, constraints, progress=progress, **options)
    b = optimize_design(design, vary, second, constraints, progress=progress, **options)
    op = "<=" if CRITERIA[second].sense == "min" else ">="
    eps = np.linspace(a.optimum.values[second], b.value, n_points)
    _say(progress, f"Pareto front {objective} vs {second}: {n_points} ε values ...")
    rows = optimize_design(
        design,
        vary,
        objective,
        constraints,
        epsilon=(second, op, eps),
        progress=progress,
        **options,
    )
    s1 = -1.0 if CRITERIA[objective].sense == "max" else 1.0
    s2 = -1.0 if CRITERIA[second].sense == "max" else 1.0
    pts = []
    for e, (d, vals, feasible) in zip(eps, rows):
        if not feasible:
            continue
        p = {"epsilon": float(e), objective: vals[objective], second: vals[second]}
        p.update({n: _jsonable(to_file_units(n, get(d, n))) for n in vary})
        pts.append(p)
    front = [
        p
        for p in pts
        if not any(
            s1 * q[objective] <= s1 * p[objective]
            and s2 * q[second] <= s2 * p[second]
            and (s1 * q[objective] < s1 * p[objective] or s2 * q[second] < s2 * p[second])
            for q in pts
        )
    ]
    front.sort(key=lambda p: s2 * p[second])
    return ParetoFront(objective, second, front, (a, b))
