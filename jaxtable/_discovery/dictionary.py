"""The discovery dictionary: candidate terms beyond the effect library, their screening with a
false-discovery rate calibrated for the whole dictionary, and the words a report uses.

Every term adds length to a leg (`jaxtable._effects.Discovered` holds their coefficients,
so a found term is a model term like any effect). A candidate is a term on a set of legs:

- shared: one coefficient for all legs (`s^2` on legs 1-6, shared);
- one leg: the term on leg i only;
- per leg: six coefficients, one per leg;
- crosstalk `s[j]`: leg j's extension on one other leg i, or on all five others (shared).

Screening (`screen`) is the score test of each candidate against the current fit, on its
linearisation: with e the whitened residuals (noise groups rescaled by VCE, as the
structure test does) and X the candidate's Jacobian columns, X⊥ = (I − H) X is what the
fitted model cannot already do with its own parameters. A candidate whose ‖X⊥‖ is below
`absorbed_below` × ‖X‖ and whose score (below) does not beat the threshold is *absorbed*:
within this workspace the geometry (and the frames and effects already in the model)
reproduce it, so the data cannot tell it apart and it would extrapolate wrongly outside.
Every candidate gets Δχ² = ‖P_X⊥ e‖² / s² (s² = ‖e‖² / dof, so σ's
scale cancels) and a penalised score Δχ² − k ln(n_obs) (k coefficients; BIC's penalty,
so per-leg terms pay for their six numbers).

Threshold: the largest penalised score over the whole dictionary has, under "nothing to
find", the law of the same maximum for Monte Carlo residuals (I − H) z (z with the rows'
correlation, masked like the data): exact for the linearised model with Gaussian noise, and
the geometry refit is inside it through H. A candidate is a discovery only when its score
beats that law's 1 − `alpha` quantile, so noise-only data yield any discovery in `alpha`
(default 5 %) of data sets, however many terms the dictionary holds.
"""

from dataclasses import dataclass, field

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .. import _params as params
from .._calibration.fit import Calibration, Setup
from .._calibration.measurements import Measurements
from .._calibration.noise import fit_basis
from .._threads import one_blas_thread
from .structure import Whitened, whitened


@dataclass(frozen=True)
class Term:
    """A family of the dictionary: its DESIGN.md string, the `Discovered` fields that hold
    it, its formula and units, what data it needs, and the words of a finding."""

    name: str
    field: str
    formula: str
    unit: str
    needs: str | None
    cause: str


TERMS = {
    t.name: t
    for t in (
        Term("s^2", "s2", "c_i s_i²", "1/mm", None, "screw sag or nonlinearity?"),
        Term("s^3", "s3", "c_i s_i³", "1/mm²", None, "nonlinear screw or encoder?"),
        Term("s[j]", "cross", "c_ij s_j", "mm/mm", None, "cable or encoder crosstalk?"),
        Term("d*s", "ds", "c_i d_i s_i", "mm/mm", None, "lead that depends on load direction?"),
        Term("T*s", "Ts", "c_i (T − 20 °C) s_i", "1/K", "temperature", "thermal scale?"),
        Term("t", "t", "c_i t (t = 0..1 over the run)", "mm", None, "warm-up or drift?"),
        Term("session*s", "session_s", "c_ki s_i (k ≥ 1)", "mm/mm", "session", "re-homing?"),
    )
}


@dataclass(frozen=True)
class TermCandidate:
    """One candidate: `term` (a DESIGN.md string, `s[j]` with j filled in), `legs` (1-based
    legs the coefficient acts on), `keys` (parameter keys in `Setup.names`), `shared`."""

    term: str
    legs: tuple
    keys: tuple
    shared: bool

    @property
    def label(self) -> str:
        if self.shared:
            return f"{self.term} on legs {_legs_text(self.legs)} (shared)"
        if len(self.legs) == 1:
            return f"{self.term} on leg {self.legs[0]}"
        return f"{self.term} on legs {_legs_text(self.legs)} (per leg)"

    def __str__(self) -> str:
        return self.label

    @property
    def family(self) -> str:
        return "s[j]" if self.term.startswith("s[") else self.term


def _legs_text(legs) -> str:
    legs = list(legs)
    if legs == list(range(legs[0], legs[-1] + 1)) and len(legs) > 2:
        return f"{legs[0]}-{legs[-1]}"
    return ", ".join(str(i) for i in legs)


def applicable_terms(data: Measurements) -> dict:
    """{term: reason} for the terms these data cannot show (no temperature variation, one
    session)."""
    out = {}
    temp = data.temperature
    if temp is None or not np.isfinite(temp).any() or np.nanmax(temp) - np.nanmin(temp) < 0.5:
        out["T*s"] = "temperature varies by less than 0.5 °C (or is absent)"
    if len(data.sessions) < 2:
        out["session*s"] = "one session only"
    return out


def candidates(st: Setup, data: Measurements) -> list[TermCandidate]:
    """Every candidate of the dictionary these data can show."""
    skip = applicable_terms(data)
    names = set(st.names)
    p = "discovered."
    out = []
    legs6 = tuple(range(1, 7))
    n_later = len(data.sessions) - 1
    for term in TERMS.values():
        if term.name in skip:
            continue
        f = term.field
        if term.name == "s[j]":
            for j in legs6:
                others = tuple(i for i in legs6 if i != j)
                out.append(TermCandidate(f"s[{j}]", others, (f"{p}cross_all[{j}]",), True))
                for i in others:
                    out.append(TermCandidate(f"s[{j}]", (i,), (f"{p}cross[{i}].{j}",), False))
            continue
        if term.name == "session*s":
            later = range(1, n_later + 1)
            out.append(
                TermCandidate(term.name, legs6, tuple(f"{p}{f}_all[{k}]" for k in later), True)
            )
            for i in legs6:
                keys = tuple(f"{p}{f}[{k}].{i}" for k in later)
                out.append(TermCandidate(term.name, (i,), keys, False))
            continue
        out.append(TermCandidate(term.name, legs6, (f"{p}{f}_all",), True))
        for i in legs6:
            out.append(TermCandidate(term.name, (i,), (f"{p}{f}[{i}]",), False))
        out.append(TermCandidate(term.name, legs6, tuple(f"{p}{f}[{i}]" for i in legs6), False))
    return [c for c in out if all(k in names for k in c.keys)]


@dataclass(frozen=True)
class Bases:
    """Orthonormal bases of what each candidate adds to a fit: for candidate c with
    (whitened) Jacobian columns X_c, Q_c spans X⊥ = (I − U Uᵀ) X_c (U: the fit's column
    space). `Q` (M, Σ r_c) all bases side by side, `bounds` (C + 1,) their column ranges,
    `kept` (C,) ‖X⊥‖ / ‖X‖ (0 for a candidate with no columns)."""

    Q: np.ndarray
    bounds: np.ndarray
    kept: np.ndarray

    @classmethod
    def of(cls, Jf: np.ndarray, U: np.ndarray, columns: list) -> "Bases":
        """`Jf` (M, P) whitened full Jacobian, `U` (M, r), `columns`: per candidate, the
        indices of its columns in `Jf`."""
        bases, kept = [], []
        for cols in columns:
            X = Jf[:, cols]
            Xp = X - U @ (U.T @ X)
            nx, nxp = np.linalg.norm(X), np.linalg.norm(Xp)
            kept.append(nxp / nx if nx > 0 else 0.0)
            bases.append(fit_basis(Xp, 1e-8) if nx > 0 and nxp > 0 else np.zeros((len(Jf), 0)))
        Q = np.concatenate(bases, axis=1) if bases else np.zeros((len(Jf), 0))
        return cls(Q, np.cumsum([0] + [q.shape[1] for q in bases]), np.asarray(kept))

    @property
    def rank(self) -> np.ndarray:
        """(C,) columns of each candidate's basis."""
        return np.diff(self.bounds)

    def delta_chi2(self, res: np.ndarray, dof: float) -> np.ndarray:
        """Δχ² (b, C) of adding each candidate to the fit, for residuals `res` (b, M) of
        that fit, in units of the noise the residuals themselves imply (s² = ‖res‖²/dof)."""
        sq = (res @ self.Q) ** 2
        csum = np.concatenate([np.zeros((len(res), 1)), np.cumsum(sq, axis=1)], axis=1)
        parts = csum[:, self.bounds[1:]] - csum[:, self.bounds[:-1]]
        scale = np.sum(res**2, axis=1, keepdims=True) / max(dof, 1.0)
        return parts / scale


@dataclass
class Screening:
    """Scores of the candidates against one fit (see the module docstring).

    `candidates`; `delta_chi2`, `score` (penalised), `kept` (‖X⊥‖/‖X‖) per candidate;
    `absorbed` (bool per candidate); `threshold`: the 1 − alpha quantile of the null law of
    the largest score; `p_value`: of the observed largest score; `coefficient` (per
    candidate: the linearised estimate, parameter units, tuple over its keys)."""

    candidates: list
    delta_chi2: np.ndarray
    score: np.ndarray
    kept: np.ndarray
    absorbed: np.ndarray
    threshold: float
    p_value: float
    coefficient: list = field(default_factory=list)

    def best(self) -> int | None:
        """Index of the highest-scoring candidate that is not absorbed (None if none)."""
        live = np.flatnonzero(~self.absorbed)
        return None if live.size == 0 else int(live[np.argmax(self.score[live])])


def null_max_scores(
    w: Whitened, basis: Bases, penalty: np.ndarray, live: np.ndarray, draws: int, seed: int
) -> np.ndarray:
    """(draws,) the largest penalised score (Δχ² − `penalty`) over the `live` candidates, for
    Monte Carlo null residuals of the fit `w` describes (`Whitened.null_draws`)."""
    out = [
        np.where(live, basis.delta_chi2(z.reshape(len(z), -1), w.dof) - penalty, -np.inf).max(1)
        for z in w.null_draws(draws, seed)
    ]
    return np.concatenate(out) if out else np.zeros(0)


def screen(
    cal: Calibration,
    st: Setup,
    cands: list,
    *,
    alpha: float = 0.05,
    draws: int = 1000,
    absorbed_below: float = 0.1,
    seed: int = 0,
    tol: float = 1e-6,
) -> Screening:
    """Score every candidate in `cands` against fit `cal` of set-up `st`, with the threshold
    that keeps the dictionary-wide false-discovery rate at `alpha` (module docstring;
    `draws=0`: scores only, threshold NaN)."""
    w = whitened(cal, st, tol)
    index = {k: i for i, k in enumerate(st.names)}
    Jf = np.asarray(cal.jacobian_full) * w.factor.reshape(-1, 1)
    n_obs = int(w.mask.sum())
    penalty = np.log(max(n_obs, 2))
    e = w.e.reshape(-1)
    basis = Bases.of(Jf, w.U, [[index[k] for k in c.keys] for c in cands])
    kept = basis.kept
    coefs = []
    for c in cands:
        X = Jf[:, [index[k] for k in c.keys]]
        Xp = X - w.U @ (w.U.T @ X)
        beta, *_ = np.linalg.lstsq(Xp, -e, rcond=1e-10)  # residual = model − measured
        coefs.append(tuple(float(b) for b in beta))
    # a term the model reproduces to 1e-3 of its norm cannot be estimated at all
    absorbed = kept < 1e-3
    k = np.array([len(c.keys) for c in cands], float)

    d_obs = basis.delta_chi2(e[None, :], w.dof)[0]
    score = d_obs - k * penalty
    null_max = null_max_scores(w, basis, k * penalty, ~absorbed, draws, seed)
    threshold = float(np.quantile(null_max, 1.0 - alpha)) if draws else float("nan")
    # absorbed: almost all of the term is what the model already does, and what is left
    # has no evidence (a term that is 99 % reproduced yet still significant is tested)
    absorbed = absorbed | ((kept < absorbed_below) & ~(score > threshold))
    live = ~absorbed
    top = score[live].max() if live.any() else -np.inf
    p = float((1 + np.sum(null_max >= top)) / (draws + 1)) if draws else float("nan")
    return Screening(list(cands), d_obs, score, kept, absorbed, threshold, p, coefs)


def words(term: str, legs: tuple, shared: bool, coef: np.ndarray, reach: float) -> str:
    """A sentence a test engineer can act on: what the term does, on which legs, how much at
    the data's reach (`reach`: the largest |extension| in the data, mm)."""
    family = "s[j]" if term.startswith("s[") else term
    cause = TERMS[family].cause
    c = np.atleast_1d(np.asarray(coef, float))
    where = (
        f"legs {_legs_text(legs)} (shared)"
        if shared
        else (f"leg {legs[0]}" if len(legs) == 1 else f"legs {_legs_text(legs)}")
    )
    vals = ", ".join
    if family == "s^2":
        what = "length error grows with extension², " + vals(
            f"{1e3 * v * reach**2:+.1f} µm" for v in c
        )
        what += f" at {reach:.0f} mm"
    elif family == "s^3":
        what = "length error grows with extension³, " + vals(
            f"{1e3 * v * reach**3:+.1f} µm" for v in c
        )
        what += f" at ±{reach:.0f} mm"
    elif family == "s[j]":
        j = term[2:-1]
        rate = vals(f"{1e3 * v:+.2f}" for v in c)
        return f"{where} follows leg {j}'s extension at {rate} µm/mm ({cause})"
    elif family == "d*s":
        what = "scale differs with the direction of travel, " + vals(
            f"{2e5 * v:+.1f} µm per 100 mm" for v in c
        )
        what += " between extending and retracting"
    elif family == "T*s":
        what = "scale grows with temperature, " + vals(f"{1e6 * v:+.1f} ppm/K" for v in c)
    elif family == "t":
        what = "length drifts over the run, " + vals(f"{1e3 * v:+.1f} µm" for v in c)
        what += " from first to last stop"
    else:  # session*s
        what = "scale changes between sessions, " + vals(f"{1e6 * v:+.0f} ppm" for v in c)
    return f"{where}: {what} ({cause})"


def term_effect(cand: TermCandidate, coefficient, n_sessions: int = 1):
    """A `Discovered` effect holding `coefficient` (one value per key of `cand`) and zero
    elsewhere: the candidate as a model term."""
    from .._effects import Discovered

    values = {f: np.array(getattr(Discovered.null(n_sessions), f)) for f in Discovered.fields}
    for key, v in zip(cand.keys, np.atleast_1d(coefficient)):
        name, _, rest = key.partition(".")[2].partition("[")
        if not rest:
            values[name] = np.asarray(float(v))
            continue
        i, _, j = rest.partition("]")
        idx = (int(i) - 1,) + ((int(j.lstrip(".")) - 1,) if j else ())
        values[name][idx] = float(v)
    return Discovered(**values)


@dataclass(frozen=True)
class DiscriminationPlan:
    """Poses that tell the members of an ambiguous group apart (`discrimination_plan`).

    - `poses` (n, 6): commanded poses, mm / rad, in the order chosen;
    - `members`: labels of the group; `correlation_before` / `correlation_after`: the largest
      canonical correlation between the first member's coefficients and any rival's in the
      joint fit (1: the data cannot tell them apart), from these data and with the plan added;
    - `separation_before` / `separation_after`: Δχ² by which the closest rival would fit
      worse if the first member, at its fitted value, is what the table does (linearised;
      NaN when the first member's value is not fitted); `context`: the conditions the plan
      assumes (dict).
    """

    poses: np.ndarray
    members: list
    correlation_before: float
    correlation_after: float
    separation_before: float
    separation_after: float
    context: dict

    @property
    def separates(self) -> bool:
        """Whether the plan makes the rivals distinguishable: the correlation drops below
        0.9 or the separation reaches Δχ² ≥ 9 (three σ)."""
        return bool(self.correlation_after < 0.9 or self.separation_after >= 9.0)

    def words(self) -> str:
        pre = (
            f"{len(self.poses)} poses (continuing session {self.context['session']}, "
            f"{self.context['temperature']:.1f} °C, payload {self.context['payload']:g} kg, "
            "each approached extending)"
        )
        figures = f"correlation of their coefficients {self.correlation_before:.2f} → " + (
            f"{self.correlation_after:.2f}"
        )
        if np.isfinite(self.separation_after):
            figures += (
                f"; the closest rival would fit worse by Δχ² {self.separation_before:.1f} → "
                f"{self.separation_after:.1f}"
            )
        if self.separates:
            return f"{pre} tell them apart ({figures})"
        return (
            f"{pre} would not tell them apart ({figures}): poses alone cannot separate "
            "them here; where they differ in the conditions (temperature, time, session, "
            "load), measure where those vary independently of each other"
        )


def _member_keys(st: Setup, member) -> list:
    if isinstance(member, TermCandidate):
        return list(member.keys)
    return params.form_keys(st.names, member)


def _canonical_correlation(cov: np.ndarray, a: list, b: list) -> float:
    """Largest canonical correlation between parameter blocks a and b of covariance cov."""
    Caa, Cbb, Cab = cov[np.ix_(a, a)], cov[np.ix_(b, b)], cov[np.ix_(a, b)]
    La, Lb = np.linalg.cholesky(Caa), np.linalg.cholesky(Cbb)
    M = np.linalg.solve(La, np.linalg.solve(Lb, Cab.T).T)
    return float(np.clip(np.linalg.svd(M, compute_uv=False)[0], 0.0, 1.0))


@one_blas_thread
def discrimination_plan(
    cal: Calibration,
    st: Setup,
    data: Measurements,
    group: list,
    n: int = 20,
    *,
    candidates: int = 1500,
    seed: int = 0,
) -> DiscriminationPlan:
    """`n` commanded poses that best tell apart the members of an ambiguous `group`
    (dictionary candidates and/or library effect names) fitted as `cal` (the final fit of
    set-up `st` on `data`).

    Ds-optimal augmentation of the run: the joint model holds every parameter `cal` frees
    plus every member's coefficients; its information from `data` (the weighted Jacobian at
    the fit) is the prior; the poses are chosen among `candidates` reachable poses, drawn in
    the box of the data's commanded poses (widened by 20 %), to maximise the information on
    the members' coefficients with everything else estimated alongside (log det F − log
    det F_nn; greedy additions, then exchange passes — `poses.select`'s search). The plan
    continues the last session (same tracker frame), at the temperature of the run's last
    tenth, with the run's most frequent payload, each pose approached extending, σ per
    column as in the data. A group whose members differ only in the conditions (a scale that
    grows with temperature, or one that changes between sessions) is not separated by
    poses: the result says so (`separates`)."""
    from .._api import actuator_command, reachable
    from .._calibration.fit import jacobian_in_chunks
    from .._calibration.poses import _greedy_exchange
    from .._context import Context

    keys = [_member_keys(st, m) for m in group]
    index = {k: i for i, k in enumerate(st.names)}
    interest = list(dict.fromkeys(k for ks in keys for k in ks))
    free = [k for k in cal.names if k not in interest]
    cols = [index[k] for k in free + interest]
    P, nI = len(cols), len(interest)
    J0 = np.asarray(cal.jacobian_full)[:, cols]
    scale = np.linalg.norm(J0, axis=0)
    scale[scale == 0] = 1.0

    # candidate rows in the same parameterisation
    cmd = np.asarray(data.cmd_pose)
    centre, half = (cmd.max(0) + cmd.min(0)) / 2, 0.6 * np.ptp(cmd, axis=0) + 1e-9
    rng = np.random.default_rng(seed)
    poses = centre + rng.uniform(-1, 1, (candidates, 6)) * half
    poses = poses[np.asarray(reachable(st.problem.nominal, poses))]
    m = len(poses)
    if m == 0:
        raise ValueError(
            "no reachable pose among the candidates drawn in the box of the data's commanded "
            "poses: no plan"
        )
    ctx0 = st.problem.ctx
    last = max(1, len(data) // 10)
    session = int(np.asarray(ctx0.session)[-1])
    T = float(np.mean(np.asarray(ctx0.temperature)[-last:]))
    loads, counts = np.unique(np.asarray(ctx0.payload), return_counts=True)
    payload = float(loads[np.argmax(counts)])
    nominal = st.problem.nominal
    s = np.asarray(actuator_command(nominal, poses, False, check=False)) - np.asarray(
        nominal.zero_lengths
    )
    w = np.asarray(cal.weight)
    wcol = np.array(
        [np.median(w[st.mask[:, k], k]) if st.mask[:, k].any() else 0.0 for k in range(6)]
    )
    ctx = Context(
        jnp.ones((m, 6)),
        jnp.full(m, T),
        jnp.full(m, payload),
        jnp.full(m, session, dtype=jnp.int32),
        jnp.ones(m),
    )
    problem = eqx.tree_at(
        lambda p: (p.s, p.guess, p.measured, p.weight, p.session, p.ctx),
        st.problem,
        (
            jnp.asarray(s),
            jnp.asarray(poses),
            jnp.zeros((m, 6)),
            jnp.asarray(np.tile(wcol, (m, 1))),
            jnp.full(m, session, dtype=jnp.int32),
            ctx,
        ),
    )
    measured = np.flatnonzero(wcol > 0)
    Jc, _, solved = jacobian_in_chunks(problem, st.layout, cal.theta)
    keep = np.flatnonzero(np.asarray(solved))  # poses the forward solve reaches
    poses = poses[keep]
    G = (np.asarray(Jc).reshape(m, 6, -1)[keep][:, measured][:, :, cols] / scale).astype(float)
    F0 = (J0 / scale).T @ (J0 / scale)
    F0 = F0 + 1e-9 * np.trace(F0) / P * np.eye(P)
    nuisance = tuple(range(P - nI))
    order, _, _ = _greedy_exchange(
        jnp.asarray(G), int(min(n, len(G))), jnp.asarray(F0), "Ds", 5, nuisance
    )
    order = np.asarray(order)
    F1 = F0 + np.einsum("imr,ims->rs", G[order], G[order])

    pos = {k: P - nI + i for i, k in enumerate(interest)}
    first = [pos[k] for k in keys[0]]

    def correlation(F):
        cov = np.linalg.inv(F)
        return max(
            _canonical_correlation(cov, first, [pos[k] for k in ks if k not in keys[0]])
            for ks in keys[1:]
            if any(k not in keys[0] for k in ks)
        )

    def separation(rows):
        """min over rivals of ‖(I − P_{free ∪ rival}) x‖², x the first member's signal."""
        if not all(k in cal.names for k in keys[0]):
            return float("nan")
        c = np.array([cal.value[cal.names.index(k)] for k in keys[0]]) * scale[first]
        x = rows[:, first] @ c
        out = []
        for ks in keys[1:]:
            B = rows[:, list(range(P - nI)) + [pos[k] for k in ks if k not in keys[0]]]
            r = x - B @ np.linalg.lstsq(B, x, rcond=1e-12)[0]
            out.append(float(r @ r))
        return min(out)

    rows0 = J0 / scale
    rows1 = np.concatenate([rows0, G[order].reshape(-1, P)])
    return DiscriminationPlan(
        poses=poses[order],
        members=[m.label if isinstance(m, TermCandidate) else params.form_label(m) for m in group],
        correlation_before=correlation(F0),
        correlation_after=correlation(F1),
        separation_before=separation(rows0),
        separation_after=separation(rows1),
        context={"session": data.sessions[session], "temperature": T, "payload": payload},
    )


def compensation_gain(cal: Calibration, st: Setup, data: Measurements, cand, coef) -> dict:
    """What compensating with a found term buys the commanded pose: the RMS pose error, at
    the data's commanded poses and contexts, of a controller that compensates with the fitted
    model minus the term, on hardware that has it (with the term the error is zero by
    construction). {"translation_rms_mm", "rotation_rms_arcsec"}."""
    import jax

    from .._api import actuator_command, forward, pose_error
    from .._rotation import ARCSEC_PER_RAD

    effects = dict(cal.effects)
    term = term_effect(cand, coef, len(data.sessions))
    without = dict(effects)
    without["discovered"] = jax.tree.map(lambda a, b: a - b, effects["discovered"], term)
    poses = np.asarray(data.cmd_pose)
    ctx = st.problem.ctx
    lengths = actuator_command(cal.table, poses, effects=without, context=ctx, check=False)
    reached = forward(cal.table, lengths, effects=effects, context=ctx, guess=poses)
    err = np.asarray(pose_error(reached, poses))
    return {
        "translation_rms_mm": float(np.sqrt(np.mean(np.sum(err[:, :3] ** 2, axis=1)))),
        "rotation_rms_arcsec": float(
            np.sqrt(np.mean(np.sum(err[:, 3:] ** 2, axis=1))) * ARCSEC_PER_RAD
        ),
    }
