"""A step in time within a session: the instrument moved (a tracker knocked, a target
re-seated) or the legs' zeros moved (the controller homed again) part-way through a
recording, and the file does not say so.

The model holds one instrument frame per session and one set of zero lengths, so a step
leaves residuals that agree in time from the step to the session's end (the structure
test's time family sees it) but that no library effect explains. The scan asks, for every
row k of a session (with at least `MIN_ROWS` measured rows on each side) and for each kind
of step, how much χ² a new set of parameters for the rows from k to the session's end would
take out of the fit's residuals: the session's frame (its fitted degrees of freedom) or the
six zero lengths, linearised at the fit. With whitened residuals e, the weighted Jacobian's
orthonormal column basis U and the kind's Jacobian columns A restricted to those rows (D_k A):

    Δχ²_k = b_kᵀ G_k⁺ b_k,   b_k = (D_k A)ᵀ e,   G_k = (D_k A)ᵀ (I − U Uᵀ)(D_k A),

each a sum over the rows from k on, so every k costs one reverse cumulative sum. The
statistic is the largest −log P(χ²_q > Δχ²_k) over rows and kinds (q the kind's rank at k);
its null law comes from Monte Carlo residuals (I − H) z of the same fit
(`structure.Whitened.null_draws`), so the scan's false-alarm rate is `alpha` for all rows
and kinds together, whatever the number of rows. A drift is not a step, though a step
part-way takes out much of it: the step is `found` only where it takes out more χ² than
a linear drift in time of the same parameters over the session (an unmodelled thermal
growth in a run whose temperature rises: split at row 73 and again at row 120 before
this rule, leaving the structure as it was).

`diagnose` scans its final model where structure is left unexplained; a step found becomes a
new session from that row (its own frame, and the library's rehoming effect can take the
zeros) and the diagnosis is made again.
"""

import dataclasses
from dataclasses import dataclass

import numpy as np

from .._calibration.fit import Calibration, Setup
from .._calibration.measurements import Measurements
from .._threads import one_blas_thread
from .structure import Whitened, clock_rows, whitened

MIN_ROWS = 10  # measured rows a session keeps on each side of a step
KINDS = ("instrument frame", "leg zeros")


@dataclass(frozen=True)
class StepInTime:
    """The strongest step of a scan (`step_scan`).

    - `row`: the first row after the step (1 = the first data row); `session`: the label
      of the session it splits; `kind`: "instrument frame" or "leg zeros";
    - `shift` (q,): the linearised step of the kind's parameters (frame dofs in mm / rad;
      zero lengths in mm per leg), `shift_std` (q,) its standard deviations (σ as the fit
      estimated it, the step's share included: on the high side), with `names` (q,);
    - `delta_chi2`: χ² it takes out (whitened residuals), on `dof` parameters;
    - `p_value`: of the largest statistic over rows and kinds (Monte Carlo, `draws`);
      `alpha`; `drift_chi2`: the χ² a linear drift in time of the same parameters over the
      session takes out; `found`: p_value < alpha and delta_chi2 > drift_chi2.
    """

    row: int
    session: str
    kind: str
    shift: np.ndarray
    shift_std: np.ndarray
    names: tuple
    delta_chi2: float
    dof: int
    p_value: float
    alpha: float
    draws: int
    drift_chi2: float = 0.0
    # {kind: (rows (R,) 1-based, Δχ² (R,))} over the step's session: the scan's profile
    profile: dict = dataclasses.field(default_factory=dict, repr=False)

    @property
    def found(self) -> bool:
        """Significant, and more a step than a drift: a linear drift in time of the same
        parameters over the session takes out less χ² (an unmodelled thermal growth is
        a drift, and a step part-way takes out much of it too)."""
        return bool(self.p_value < self.alpha and self.delta_chi2 > self.drift_chi2)

    def shift_words(self) -> str:
        parts = []
        for name, v, sd in zip(self.names, self.shift, self.shift_std):
            if name.endswith((".roll", ".pitch", ".yaw")):
                f, unit, what = np.rad2deg(3600.0), "″", name.rsplit(".", 1)[1]
            else:
                f, unit = 1e3, " µm"
                what = f"leg {name[-2]}" if self.kind == "leg zeros" else name.rsplit(".", 1)[1]
            parts.append(f"{what} {f * v:+.3g} ± {f * sd:.2g}{unit}")
        return ", ".join(parts)

    def words(self) -> str:
        what = (
            "the instrument moved"
            if self.kind == "instrument frame"
            else "the legs' zeros moved (homed again)"
        )
        verdict = (
            ""
            if self.found
            else "not significant: "
            if self.p_value >= self.alpha
            else f"a drift rather than a step (a linear drift takes Δχ² = {self.drift_chi2:.1f}): "
        )
        return (
            f"{verdict}the residuals step at row {self.row} (session {self.session}): "
            f"{what} ({self.shift_words()}; Δχ² = {self.delta_chi2:.1f} on {self.dof}, "
            f"p = {self.p_value:.3g})"
        )

    def as_json(self) -> dict:
        return {
            "row": self.row,
            "session": self.session,
            "kind": self.kind,
            "shift": {n: float(v) for n, v in zip(self.names, self.shift)},
            "shift_std": {n: float(v) for n, v in zip(self.names, self.shift_std)},
            "units": "mm, rad",
            "delta_chi2": self.delta_chi2,
            "dof": self.dof,
            "p_value": self.p_value,
            "alpha": self.alpha,
            "draws": self.draws,
            "drift_chi2": self.drift_chi2,
            "found": self.found,
        }


def _columns(cal: Calibration, session: int) -> dict:
    """{kind: indices of its columns in `cal.jacobian`} for a session (0-based)."""
    frame = [i for i, n in enumerate(cal.names) if n.startswith(f"frame[{session + 1}].")]
    zeros = [i for i, n in enumerate(cal.names) if n.startswith("zero_lengths[")]
    return {k: v for k, v in zip(KINDS, (frame, zeros)) if v}


def _pinv_stack(G: np.ndarray, rtol: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """Pseudo-inverses (K, q, q) of symmetric positive semi-definite G (K, q, q) and their
    ranks (K,)."""
    lam, V = np.linalg.eigh(G)
    keep = lam > rtol * np.maximum(lam[:, -1:], 1e-300)
    inv = np.where(keep, 1.0 / np.where(keep, lam, 1.0), 0.0)
    return np.einsum("kij,kj,klj->kil", V, inv, V), keep.sum(axis=1)


@dataclass(frozen=True)
class _Kind:
    """One kind of step in one session: candidate rows `k` (R,), the (R, q, q)
    pseudo-inverses of G_k and ranks, the (n, 6, q) whitened columns A on the session's
    rows `rows` (n,), and the column indices `cols`."""

    session: int
    kind: str
    cols: list
    rows: np.ndarray
    k: np.ndarray
    A: np.ndarray
    Ginv: np.ndarray
    rank: np.ndarray
    ramp: np.ndarray  # (n, 6, q) the columns A times the centred time of each row
    ramp_inv: np.ndarray  # (q, q) pseudo-inverse of the ramp's G
    ramp_rank: int = 0  # its rank: the drift's degrees of freedom

    def drift_chi2(self, e: np.ndarray) -> float:
        """Δχ² a linear drift in time of the kind's parameters over the session takes out
        of whitened residuals e (N, 6)."""
        b = np.einsum("nc,ncq->q", e[self.rows], self.ramp)
        return float(b @ self.ramp_inv @ b)

    def delta_chi2(self, e: np.ndarray) -> np.ndarray:
        """(..., R) Δχ²_k of whitened residuals e (..., N, 6)."""
        c = np.einsum("...nc,ncq->...nq", e[..., self.rows, :], self.A)
        b = np.flip(np.cumsum(np.flip(c, -2), -2), -2)[..., self.k, :]
        return np.einsum("...kq,kqp,...kp->...k", b, self.Ginv, b)


def _kinds(cal: Calibration, st: Setup, w: Whitened, min_rows: int) -> list:
    J = np.asarray(cal.jacobian) * w.factor.reshape(-1, 1)
    n = len(w.mask)
    U = w.U.reshape(n, 6, -1)
    session = np.asarray(st.problem.session)
    measured = w.mask.any(axis=1)
    clock = clock_rows(st.problem.ctx.time)  # a drift is linear in time, across pauses too
    out = []
    for s in np.unique(session[measured]):
        rows = np.flatnonzero((session == s) & measured)
        if len(rows) < 2 * min_rows:
            continue
        k = np.arange(min_rows, len(rows) - min_rows + 1)  # positions in `rows`
        for kind, cols in _columns(cal, int(s)).items():
            A = J[:, cols].reshape(n, 6, -1)[rows]
            tail = lambda x: np.flip(np.cumsum(np.flip(x, 0), 0), 0)[k]  # noqa: E731
            AA = tail(np.einsum("ncq,ncp->nqp", A, A))
            M = tail(np.einsum("ncr,ncq->nrq", U[rows], A))
            G = AA - np.einsum("krq,krp->kqp", M, M)
            Ginv, rank = _pinv_stack(G)
            t = clock[rows] - np.mean(clock[rows])
            R = A * t[:, None, None]
            MR = np.einsum("ncr,ncq->rq", U[rows], R)
            GR = np.einsum("ncq,ncp->qp", R, R) - MR.T @ MR
            ramp_inv, ramp_rank = (x[0] for x in _pinv_stack(GR[None]))
            out.append(
                _Kind(int(s), kind, cols, rows, k, A, Ginv, rank, R, ramp_inv, int(ramp_rank))
            )
    return out


@dataclass(frozen=True)
class DriftSource:
    """Whose drift a drift in time is: what a linear drift over each session of the
    instrument's frame (its fitted degrees of freedom) and of the six legs' zeros take out
    of a fit's whitened residuals (`chi2` {kind: Δχ²}, `dof` {kind: q}, linearised at the
    fit, summed over sessions), each scored as the dictionary scores a term, Δχ² − q ln n
    (`n_obs` readings). The two are different functions of the pose (a frame drift moves
    every reading alike; a drift of the legs' zeros moves the platform by J⁻¹ c, which
    changes over the workspace), so the data can prefer one: `preferred` is the kind
    whose score is higher by more than `margin` (the dictionary's ambiguity), else
    "either"."""

    chi2: dict
    dof: dict
    n_obs: int
    margin: float

    def score(self, kind: str) -> float:
        return self.chi2[kind] - self.dof[kind] * np.log(self.n_obs)

    @property
    def preferred(self) -> str:
        if len(self.chi2) < 2:
            return "either"
        frame, legs = self.score("instrument frame"), self.score("leg zeros")
        if abs(frame - legs) <= self.margin:
            return "either"
        return "instrument frame" if frame > legs else "leg zeros"

    def words(self) -> str:
        if len(self.chi2) < 2:
            return ""
        numbers = (
            f"a drift of the instrument's frame over each session takes out Δχ² = "
            f"{self.chi2['instrument frame']:.1f} on {self.dof['instrument frame']}, one of "
            f"the six legs' zeros {self.chi2['leg zeros']:.1f} on {self.dof['leg zeros']}"
        )
        if self.preferred == "instrument frame":
            return (
                f"{numbers}: the instrument drifting (a tracker or its stand warming up, a "
                "target creeping) reads like this more than the legs do; compensating the "
                "table's commands for it would move the table off"
            )
        if self.preferred == "either":
            return (
                f"{numbers}: the legs or the instrument, these data cannot tell; a fixed "
                "reference target read now and then would"
            )
        return f"{numbers}: the legs', not the instrument's"

    def as_json(self) -> dict:
        return {
            "delta_chi2": dict(self.chi2),
            "dof": dict(self.dof),
            "preferred": self.preferred,
            "words": self.words(),
        }


def drift_source(cal: Calibration, st: Setup, margin: float = 6.0) -> DriftSource:
    """`DriftSource` of fit `cal` (set-up `st`): the instrument frame's drift against the
    legs' zeros', over every session with 4 measured rows or more."""
    w = whitened(cal, st)
    chi2, dof = {}, {}
    for kd in _kinds(cal, st, w, 2):
        chi2[kd.kind] = chi2.get(kd.kind, 0.0) + kd.drift_chi2(w.e)
        dof[kd.kind] = dof.get(kd.kind, 0) + kd.ramp_rank
    return DriftSource(chi2, dof, int(np.asarray(w.mask).sum()), margin)


def _log_sf(d: np.ndarray, rank: np.ndarray) -> np.ndarray:
    """−log P(χ²_rank > d), elementwise (rank 0: 0): the ufunc `chdtrc`, and where that
    underflows (d beyond ~1,400: a step in a long log, whose fit has the degrees of
    freedom for it), the asymptotic series of
    the upper incomplete gamma function, log Q(a, x) = −x + (a − 1) log x − log Γ(a) +
    log(1 + (a − 1)/x + (a − 1)(a − 2)/x² + …), a = rank/2, x = d/2 (scipy.stats' `logsf`
    returns inf there, and a tie at inf would pick the first row, not the strongest)."""
    from scipy.special import chdtrc, gammaln

    d, q = np.broadcast_arrays(np.asarray(d, float), np.maximum(rank, 1))
    sf = chdtrc(q, d)
    out = -np.log(np.maximum(sf, 1e-300))
    low = sf < 1e-290
    if low.any():
        a, x = q[low] / 2.0, d[low] / 2.0
        series = 1.0 + (a - 1.0) / x + (a - 1.0) * (a - 2.0) / x**2
        out[low] = x - (a - 1.0) * np.log(x) + gammaln(a) - np.log(series)
    return np.where(rank > 0, out, 0.0)


@one_blas_thread
def step_scan(
    cal: Calibration,
    st: Setup,
    *,
    alpha: float = 0.01,
    draws: int = 1000,
    seed: int = 0,
    min_rows: int = MIN_ROWS,
) -> StepInTime | None:
    """The strongest step in time of fit `cal` (set-up `st`) over every session, row and
    kind, with its family-wise p-value (see the module docstring); None where no session
    has 2 × `min_rows` measured rows. `alpha`: false-alarm rate; `draws`: Monte Carlo
    draws of the null law."""
    w = whitened(cal, st)
    kinds = _kinds(cal, st, w, min_rows)
    if not kinds:
        return None
    stats = [_log_sf(kd.delta_chi2(w.e), kd.rank) for kd in kinds]
    best = int(np.argmax([s.max() for s in stats]))
    kd, at = kinds[best], int(np.argmax(stats[best]))
    observed = float(stats[best][at])
    null = np.concatenate(
        [
            np.max([_log_sf(kd_.delta_chi2(z), kd_.rank).max(axis=-1) for kd_ in kinds], axis=0)
            for z in w.null_draws(draws, seed)
        ]
    )
    p = float((1 + np.sum(null >= observed)) / (draws + 1))
    # the step itself: G⁺ b in whitened units is the parameters' change (the columns are
    # the Jacobian's own, so the units are the parameters')
    c = np.einsum("nc,ncq->nq", w.e[kd.rows], kd.A)
    b = c[kd.k[at] :].sum(axis=0)
    shift = -kd.Ginv[at] @ b  # residual = model − measured
    session_labels = st.noise.sessions if st.noise is not None else ("1",)
    return StepInTime(
        row=int(kd.rows[kd.k[at]]) + 1,
        session=str(session_labels[kd.session]),
        kind=kd.kind,
        shift=shift,
        shift_std=np.sqrt(np.clip(np.diag(kd.Ginv[at]), 0.0, None)),
        names=tuple(cal.names[i] for i in kd.cols),
        delta_chi2=float(b @ kd.Ginv[at] @ b),
        dof=int(kd.rank[at]),
        p_value=p,
        alpha=alpha,
        draws=draws,
        drift_chi2=kd.drift_chi2(w.e),
        profile={
            k.kind: (k.rows[k.k] + 1, k.delta_chi2(w.e)) for k in kinds if k.session == kd.session
        },
    )


def split_session(data: Measurements, row: int, label: str) -> Measurements:
    """`data` with the rows of `row`'s session from `row` (0-based) on given the session
    `label` (a copy)."""
    session = np.array(data.session, dtype=object)
    later = (np.arange(len(data)) >= row) & (session == session[row])
    if np.any(session == label):
        raise ValueError(f"session label {label!r} is already in use")
    session[later] = label
    return dataclasses.replace(data, session=session.astype(str))


def split_label(data: Measurements, step: StepInTime) -> str:
    """The label of the new session from `step`: '<session>@<row>' (primes added while the
    label is taken)."""
    label = f"{step.session}@{step.row}"
    while label in data.sessions:
        label += "'"
    return label


@dataclass(frozen=True)
class SessionSplit:
    """A session `diagnose` split at a step in time: the `step`, the new session's `label`,
    and the held-out RMS (σ-normalised in the final model's σ, the same folds) of the
    final model of the diagnosis before the split and of the final diagnosis."""

    step: StepInTime
    label: str
    heldout_rms_before: float = float("nan")
    heldout_rms_after: float = float("nan")

    def words(self) -> str:
        from .._calibration.heldout import heldout_text

        return (
            f"{self.step.words()}; rows {self.step.row}… of session {self.step.session} "
            f"diagnosed as session '{self.label}': held-out RMS "
            f"{heldout_text(self.heldout_rms_before)} -> "
            f"{heldout_text(self.heldout_rms_after, suffix=' sigma')}"
        )

    def as_json(self) -> dict:
        return {
            **self.step.as_json(),
            "label": self.label,
            "heldout_rms_before": self.heldout_rms_before,
            "heldout_rms_after": self.heldout_rms_after,
        }
