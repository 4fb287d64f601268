"""Gross errors in measured data: readings a fit cannot reconcile with the rest (a tracker's
beam broken for one reading, a target re-seated, a value typed into the wrong row).

The test is data snooping with a robust scale, on a model that fits: where the fit's
residuals show structure (`_discovery.structure`), a gross error cannot be told from the
tails of what the model misses, and the callers do not screen (an unmodelled thermal drift
otherwise had readings set aside; a few gross errors do not raise that test: p = 0.76 with
four planted in 80 stops). For every fitted reading i the studentised
residual w_i = e_i / √r_i (e_i the σ-normalised residual, r_i = 1 − H_ii its redundancy
number: the part of an error the fit cannot absorb) is divided by its noise group's robust
scale, 1.4826 × the median |w| over the group (a few gross errors do not inflate it, as they
do the fit's σ). Readings beyond the two-sided normal quantile at α / (2 M) (M tested
readings: a family-wise false-alarm rate α on clean data; Student's t rather than the normal
law, for the scale's own error) are gross errors; per round only the largest (beyond its
bound) is set aside (a gross error pulls the fit, and with it readings that are fine:
a 1 mm error in one x reading moved ten others past the bound), the model is refitted and
the test repeated until none is left. Each is then reported with its residual from the
final model, fitted without it (the whole error, not the part the fit left). Readings with a
redundancy under `MIN_REDUNDANCY` are not tested: the fit absorbs an error there, whatever
its size (the report counts them). A reading far out whose neighbours (in time and in the
legs' extensions) are far out the same way is not a gross error but structure the model
misses, and is kept (`screen`): without that rule an unmodelled thermal drift had 52 of its
readings set aside.
"""

from dataclasses import dataclass, replace
from statistics import NormalDist

import numpy as np

from .._distributions import t_ppf
from .._errors import POSE_COLUMNS
from .._rotation import euler_from_matrix, euler_matrices, rotation_log
from .noise import robust_scales

# readings no table could have produced (`blunders`): off the commanded pose, through the
# instrument's rigid registration, by more than both of these
BLUNDER_MM, BLUNDER_DEG = 5.0, 0.5  # mm, degrees: ~10x a rough table's pose errors
BLUNDER_SCALE = 20.0  # robust σ of the session's registration residuals
BLUNDER_SHARE = 0.2  # more of a session's readings than this: the model is off, not them
BLUNDER_WORDS = f"off the commanded pose by more than {BLUNDER_MM:g} mm or {BLUNDER_DEG:g}°"
# rows that repeat an earlier row to the last written digit (`repeats`): the finest noise a
# table's instrument has (mm, degrees; an interferometer's 0.1 µm, an autocollimator's 0.1″)
# and the chance of such a coincidence under it below which a repeat is a stop logged twice
REPEAT_FLOOR = np.array([1e-4] * 3 + [0.1 / 3600] * 3)
REPEAT_CHANCE = 1e-6
MIN_REDUNDANCY = 0.05
ALPHA = 0.01
ALONE = 2.5  # mean neighbour z (own direction) below which a reading stands alone
BURST = 5  # the most readings in a row (one column, in time) a gross error may come in
TRIAL_ROUNDS = 10  # gross errors the screen may set aside where the fit shows structure


@dataclass(frozen=True)
class GrossError:
    """One reading set aside: `row` (1 = the first data row), `column` (x … yaw),
    `residual` (measured − model, mm or degrees), `z` (studentised, in robust σ)."""

    row: int
    column: str
    residual: float
    z: float

    def words(self) -> str:
        unit = "mm" if self.column in POSE_COLUMNS[:3] else "°"
        return f"row {self.row} {self.column} {self.residual:+.4g} {unit} ({self.z:+.0f}σ)"


@dataclass(frozen=True)
class Repeat:
    """A row (1 = the first data row) that repeats the earlier row `of`: the same command
    and every reading to the last digit."""

    row: int
    of: int

    def words(self) -> str:
        return f"row {self.row} = row {self.of}"


def repeat_words(found) -> str:
    """`Repeat`s in words for logs and reports ("" for none)."""
    if not found:
        return ""
    shown = "; ".join(r.words() for r in found[:10])
    more = f"; ... and {len(found) - 10} more" if len(found) > 10 else ""
    return (
        f"{len(found)} row(s) repeat an earlier row's command and readings to the last digit "
        f"(a stop logged twice, or a stale reading), set aside before any fit: {shown}{more}"
    )


def written_step(values) -> np.ndarray:
    """The decimal step each value is written to (10⁻ᵏ for the least k that makes it a whole
    number of steps, to rounding), elementwise; a value in full double precision gets a step
    near its own rounding (~1e-15 of it). NaN where the value is not finite."""
    v = np.asarray(values, float)
    step = np.full(v.shape, np.nan)
    for k in range(18):  # the decimals a double can carry
        x = v * 10.0**k
        whole = np.abs(x - np.round(x)) <= 1e-6 + 8 * np.finfo(float).eps * np.abs(x)
        step = np.where(np.isnan(step) & whole & np.isfinite(v), 10.0**-k, step)
    return step


def repeats(data) -> list:
    """`Repeat`s: rows whose command and readings (the same cells read, every value equal)
    equal an earlier row's, each named with the first row it repeats. A logger that wrote a
    stop twice, an instrument that returned its last value again, or a file joined with part
    of itself give such rows; counted twice, a stop weighs double in every fit and its
    residual agrees exactly with its twin's, which the structure test takes for structure
    (15 repeated rows in 150 clean stops: structure claimed, p = 0.002). Two real readings
    agree to the last digit by chance: with a written step q and noise σ, two readings of one
    column coincide with chance ≈ q / (2√π σ). A row is a repeat where the product of that
    chance over its readings, with σ at the finest noise a table's instrument has
    (`REPEAT_FLOOR`), is under `REPEAT_CHANCE`, or where the file's clock, which otherwise
    moves from row to row, gives both rows the same time. Readings written to a micrometre,
    without a clock, are therefore not screened: equal readings there can be chance."""
    cmd = np.asarray(data.cmd_pose, float)
    measured = np.asarray(data.measured, float)
    n = len(cmd)
    key = np.concatenate([cmd, measured], axis=1) + 0.0  # −0 as 0
    key = np.where(np.isnan(key), np.nan, key).view(np.int64)  # one NaN; bits compare
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    first = first[np.ravel(inverse)]
    read = np.isfinite(measured)
    candidate = (first < np.arange(n)) & read.any(axis=1)
    if not candidate.any():
        return []
    values = np.concatenate([measured[:, :3], np.rad2deg(measured[:, 3:])], axis=1)
    step = written_step(values)
    chance = np.where(read, np.minimum(1.0, step / (2 * np.sqrt(np.pi) * REPEAT_FLOOR)), 1.0)
    same = np.prod(chance, axis=1) < REPEAT_CHANCE
    if data.time is not None:  # the same time on a clock that moves: the same stop
        clock = np.asarray(data.time, float)
        moves = np.abs(np.diff(clock[np.isfinite(clock)]))
        if len(moves) and np.median(moves) > 0:
            same |= clock == clock[first]
    rows = np.flatnonzero(candidate & same)
    return [Repeat(int(r) + 1, int(first[r]) + 1) for r in rows]


def repeated_cells(data, found) -> list:
    """The (row index, column index) readings of the `Repeat` rows `found`, for `without`."""
    read = np.isfinite(np.asarray(data.measured, float))
    return [(r.row - 1, int(c)) for r in found for c in np.flatnonzero(read[r.row - 1])]


def prescreen(data):
    """Before any fit: the rows a logger wrote twice (`repeats`), then the readings no table
    could have produced (`blunders`), set aside (`without`). Returns (data without them,
    `Repeat`s, `GrossError`s)."""
    found = repeats(data)
    if found:
        data = without(data, repeated_cells(data, found))
    pre = blunders(data)
    if pre:
        data = without(data, pre)
    return data, found, pre


def without(data, cells):
    """`data` (Measurements) with the readings `cells` — (row index, column index) pairs or
    `GrossError`s (1-based rows, column names) — set to not measured (NaN) and marked in
    `aside` (the instrument read them: `noise.noise_model` keeps each row's set of columns);
    a copy."""
    measured = np.array(data.measured, float)
    aside = np.zeros(measured.shape, bool) if data.aside is None else np.array(data.aside, bool)
    for cell in cells:
        if isinstance(cell, GrossError):
            cell = (cell.row - 1, POSE_COLUMNS.index(cell.column))
        measured[cell[0], cell[1]] = np.nan
        aside[cell[0], cell[1]] = True
    return replace(data, measured=measured, aside=aside)


def threshold(tested: int, alpha: float = ALPHA, group: int | None = None) -> float:
    """|z| beyond which a reading is a gross error: the two-sided quantile at α / (2 M) for
    M tested readings, of Student's t with the degrees of freedom of a median-based scale
    from `group` readings (0.37 per reading, the median's efficiency at the normal law; the
    normal law when `group` is None). With the normal quantile, the scale's own error
    (about 8 % from 180 readings) raised the false-alarm rate to 2.2 % (1000 clean data
    sets of 60 stops)."""
    q = 1.0 - alpha / (2.0 * max(tested, 1))
    if group is None:
        return NormalDist().inv_cdf(q)
    return float(t_ppf(q, max(0.37 * group, 3.0)))


def screen(cal, mask, groups, extensions, session, alpha: float = ALPHA):
    """The largest gross error of fit `cal` (a `Calibration` with its residuals, weights and
    redundancy numbers) over the fitted readings `mask` (N, 6), noise `groups` (N, 6)
    (−1: none), if any; `extensions` (N, 6) the legs' extensions and `session` (N,) the
    session index of each stop, for its neighbours.

    A reading beyond its bound is a gross error only if it stands alone: in its own
    direction, the mean z of the same column at the stops before and after it (same
    session), and the mean at the three stops nearest in the legs' extensions, are each
    under `ALONE` (each about N(0, 1/2) or N(0, 1/3) beside a true gross error, so 3.5 and
    4.3 sd below it; a gross error pulls them the other way if anything; at 1.5, a planted
    error lost to noise of +1.0σ and +2.3σ at its two stops in time). A model that misses a
    smooth effect (a thermal drift) leaves readings far out whose neighbours are far out
    too: structure, not gross errors, and kept. Gross errors can come in a burst (a
    tracker that lost its beam for three readings: each the others' neighbour, all far
    out): the stops before and after are those past readings beyond their bound the same
    way, at most `BURST` in a row with it (a longer run is structure), and the three stops
    nearest in extensions are those not of its burst and not beyond their bound the same
    way, among its 3 + `BURST` nearest (more of those beyond: structure).

    Returns ((row index, column index, z) or None; readings tested; readings not testable;
    readings beyond their bound that did not stand alone). z is measured − model in robust
    σ."""
    n = mask.shape[0]
    e = np.asarray(cal.residual, float).reshape(n, 6)
    red = np.asarray(cal.redundancy, float).reshape(n, 6)
    fitted = mask & (np.asarray(cal.weight) > 0)
    testable = fitted & (red >= MIN_REDUNDANCY)
    w = np.where(testable, e / np.sqrt(np.where(testable, red, 1.0)), 0.0)
    z = np.zeros_like(w)
    bound = np.full(w.shape, np.inf)
    tested = int(testable.sum())
    labels = np.unique(groups[testable])
    scales = robust_scales(e, red, groups, testable, int(labels.max(initial=-1)) + 1, min_red=0.0)
    for g in labels:
        cells = testable & (groups == g)
        scale = scales[g]
        if scale > 0:
            z[cells] = w[cells] / scale
            bound[cells] = threshold(tested, alpha, int(cells.sum()))
    untested = int((fitted & ~testable).sum())
    far = np.argwhere(np.abs(z) > bound)
    far = far[np.argsort(-(np.abs(z) - bound)[far[:, 0], far[:, 1]])]
    x = np.asarray(extensions, float)
    x = (x - x.mean(0)) / np.where(x.std() > 0, x.std(), 1.0)
    session = np.asarray(session)
    crowded = 0
    for r, c in far:
        # the readings next to it in time, past a burst of at most BURST readings beyond
        # their bound the same way (a beam lost for several readings: each other's
        # neighbours, and all far out)
        beyond = testable[:, c] & (np.sign(z[r, c]) * z[:, c] > bound[:, c])
        side, burst = [], [r]
        for step in (-1, 1):
            k, run = r + step, []
            while 0 <= k < n and session[k] == session[r]:
                if testable[k, c] and not beyond[k]:
                    side.append(k)
                    break
                if testable[k, c]:
                    run.append(k)
                    if len(run) >= BURST:
                        break
                k += step
            burst += run
        # the three stops nearest in the legs' extensions, past at most BURST beyond their
        # bound the same way (gross errors at stops close in extension)
        others = np.flatnonzero(testable[:, c])
        others = others[~np.isin(others, burst)]
        others = others[np.argsort(np.sum((x[others] - x[r]) ** 2, axis=1))]
        nearest = others[: 3 + BURST]
        near = nearest[~beyond[nearest]][:3]
        # a long run or a crowd far out the same way: structure
        long = len(burst) > BURST or beyond[nearest].sum() > BURST
        if long or any(
            len(nb) and np.mean(np.sign(z[r, c]) * z[nb, c]) >= ALONE for nb in (near, side)
        ):
            crowded += 1
            continue
        # residual = model − measured; z as measured − model
        return (int(r), int(c), -float(z[r, c])), tested, untested, crowded
    return None, tested, untested, crowded


def _rigid(P, Rc, Q, rows):
    """Instrument frame (R, t) and target offset a (platform frame) with Q ≈ R (P + Rc a) + t
    over `rows` of P, Q (N, 3), Rc (N, 3, 3): Gauss-Newton on (rotation increment, t, a)
    from the Kabsch frame with a = 0 (alternating the two converged too slowly: a target
    150 mm off took tens of rounds)."""
    from .fit import _kabsch

    P, Q, Rc = P[rows], Q[rows], Rc[rows]
    R, t = _kabsch(P, Q)
    a = np.zeros(3)
    eye = np.broadcast_to(np.eye(3), (len(P), 3, 3))
    for _ in range(8):
        X = (P + Rc @ a) @ R.T  # R (P + Rc a), (M, 3)
        r = (Q - X - t).reshape(-1)
        skew = np.zeros((len(P), 3, 3))  # −[X]×: the change of R X for a turn ω
        skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = X[:, 2], -X[:, 1], X[:, 0]
        skew -= np.swapaxes(skew, 1, 2)
        J = np.concatenate([skew, eye, R @ Rc], axis=2).reshape(-1, 9)
        step = np.linalg.lstsq(J, r, rcond=None)[0]
        w = step[:3]
        turn = np.eye(3) + np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        U, _, Vt = np.linalg.svd(turn @ R)  # the nearest rotation
        R = U @ Vt
        t, a = t + step[3:6], a + step[6:]
    return R, t, a


def _trimmed(fit, distance, rows: np.ndarray):
    """`fit(keep)` of the rows `rows` (N,) bool, robustly: fitted again on the better half of
    them by `distance(model)` (N,), then twice on those within 5× the median distance of
    the rows kept (a fifth of the rows far off bent a plain fit). Returns the last model."""
    keep = rows.copy()
    for k in range(4):
        model = fit(keep)
        d = np.where(rows, distance(model), np.inf)
        keep = rows & (d <= (np.median(d[rows]) if k == 0 else 5 * np.median(d[keep]) + 1e-12))
    return model


def _chordal_mean(Rs: np.ndarray) -> np.ndarray:
    """The rotation nearest the mean of rotations Rs (M, 3, 3), robustly (`_trimmed`, by the
    angle from it)."""

    def mean(keep):
        U, _, Vt = np.linalg.svd(Rs[keep].mean(axis=0))
        return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt

    def angle(M):
        return np.linalg.norm(rotation_log(np.swapaxes(Rs, 1, 2) @ M), axis=1)

    return _trimmed(mean, angle, np.ones(len(Rs), bool))


def _column_medians(x: np.ndarray) -> np.ndarray:
    """(C,) the median of each column of x (N, C) over its finite cells; NaN for a column
    with none (a column the instrument does not read), without numpy's warning."""
    ok = np.isfinite(x).any(axis=0)
    out = np.full(x.shape[1], np.nan)
    out[ok] = np.nanmedian(x[:, ok], axis=0)
    return out


def _registration_residual(cmd: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """(N, 6) measured − the commanded poses (N, 6, mm / rad) read through a rigid instrument
    frame and target offset registered on the rows themselves, robustly (`_trimmed`; angles
    by a trimmed mean rotation): what a table's own errors
    and the noise leave, plus any blunder whole. Angle columns wrapped, rad; NaN where not
    measured. Rows without all three positions (or angles) are compared column by column."""
    Rc = euler_matrices(cmd[:, 3:])
    P, Q = cmd[:, :3], measured[:, :3]
    out = np.full(cmd.shape, np.nan)
    complete = np.isfinite(Q).all(axis=1)
    RF = np.eye(3)
    if complete.sum() >= 6:

        def residual(model):
            RF, t, a = model
            return Q - ((P + Rc @ a) @ RF.T + t)

        model = _trimmed(
            lambda keep: _rigid(P, Rc, Q, keep),
            lambda m: np.linalg.norm(residual(m), axis=1),
            complete,
        )
        RF = model[0]
        out[:, :3] = residual(model)
    else:  # a column's offset: the median difference
        d = Q - P
        out[:, :3] = d - _column_medians(d)
    A = measured[:, 3:]
    full = np.isfinite(A).all(axis=1)
    if full.sum() >= 6:
        Rm = euler_matrices(np.where(np.isfinite(A), A, 0.0))
        if complete.sum() >= 6:  # the frame's rotation from the positions: the target's here
            RT = _chordal_mean(np.swapaxes(Rc, 1, 2)[full] @ RF.T @ Rm[full])
            pred = RF @ Rc @ RT
        else:
            pred = _chordal_mean(Rm[full] @ np.swapaxes(Rc[full], 1, 2)) @ Rc
        angles = np.asarray(euler_from_matrix(np.moveaxis(pred, 0, -1))).T
    else:
        angles = cmd[:, 3:] + _column_medians(A - cmd[:, 3:])
    out[:, 3:] = np.mod(A - angles + np.pi, 2 * np.pi) - np.pi
    return out


def blunders(data) -> list:
    """`GrossError`s (largest first) of the readings no table could have produced: a tracker
    that lost its target and logged zeros, a sentinel (−9999) or a stale reading. Each
    session's readings are compared with its commanded poses through a rigid instrument
    frame and target offset registered on the session robustly (`_registration_residual`);
    a reading is a blunder where it is off by more than `BLUNDER_MM` (positions) or
    `BLUNDER_DEG` (angles) and by more than `BLUNDER_SCALE` robust σ of the session's
    residuals in its group (1.4826 × the median absolute residual); a row with more than
    half of its readings so far off lost the target for that stop, and all of them are
    blunders. A table's own errors move its poses by tenths of a millimetre, so that these
    readings are set aside before
    any fit: a few of them otherwise corrupt the fit and its noise estimate, and the
    structure they leave stops the gross-error screen. A session where more than
    `BLUNDER_SHARE` of the readings would be set aside keeps them all (the commanded poses
    or the file's units are off, and the checks and the fit say so). `z` is in those
    robust σ; `residual` in mm or degrees, from the registration."""
    cmd, measured = np.asarray(data.cmd_pose, float), np.asarray(data.measured, float)
    out = []
    for k in range(len(data.sessions)):  # a handful of sessions
        rows = np.flatnonzero(data.session_index == k)
        r = _registration_residual(cmd[rows], measured[rows])
        z = np.zeros_like(r)
        far = np.zeros(r.shape, bool)
        for cols, floor in ((slice(0, 3), BLUNDER_MM), (slice(3, 6), np.deg2rad(BLUNDER_DEG))):
            e = r[:, cols]
            scale = 1.4826 * np.nanmedian(np.abs(e)) if np.isfinite(e).any() else np.nan
            if not np.isfinite(scale) or scale <= 0:
                continue
            z[:, cols] = e / scale
            far[:, cols] = np.abs(e) > max(floor, BLUNDER_SCALE * scale)
        far &= np.isfinite(r)
        # a row with most of its readings off lost the target for that stop: all of them
        lost = far.sum(axis=1) * 2 > np.isfinite(r).sum(axis=1)
        far |= lost[:, None] & np.isfinite(r)
        if far.sum() > BLUNDER_SHARE * np.isfinite(measured[rows]).sum():
            continue
        for i, c in zip(*np.nonzero(far)):
            value = r[i, c] if c < 3 else np.rad2deg(r[i, c])
            out.append(GrossError(int(rows[i]) + 1, POSE_COLUMNS[c], float(value), float(z[i, c])))
    return sorted(out, key=lambda g: -abs(g.z))
