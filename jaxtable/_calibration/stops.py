"""Several readings of one stop: consecutive rows of a session with the same command (a
logger that reads the tracker a few times while the table holds a pose).

The readings of one stop share the table's error at that stop (its repeatability: where
the legs settled this time, the backlash taken up, the air the beam crossed during those
seconds), so they are not independent readings of the model: fitted row by row, a stop
read five times weighs five times, its shared error agrees between its rows, and the
structure test reads that agreement as structure (60 stops read 5 times, tracker σ 5 µm
and a repeatability of 3 µm: structure claimed, p = 0.001, in 4 of 4 data sets).
`merge_stops` fits each stop once, at the mean of its readings: the generalised least
squares of the two-level noise (σ² within a stop plus the stop's own error) when every
stop has the same number of readings, since the model predicts the same reading for all
rows of a stop. The scatter of the readings about their stop's mean is the instrument's
noise without any model (pure error); the stop means' scatter about the fitted model,
beyond that noise over √k, is the table's repeatability at a stop (`Stops.words`).

The mean goes into the stop's first row and the other rows' readings are set aside
(`Measurements.aside`, not measured), so that every row keeps its number in reports, and
the context (direction of travel, clock) is the file's.
"""

from dataclasses import dataclass, field, replace

import numpy as np

from .._distributions import f_sf
from .._rotation import ARCSEC_PER_RAD, wrap_reading_difference

GROUPS = {"positions": slice(0, 3), "angles": slice(3, 6)}


@dataclass(frozen=True)
class Stops:
    """Stops read more than once: `stops` of them, over `rows` rows; `per_stop` the median
    rows a stop of those; `within` {group: (σ, dof)}: the pooled scatter of a stop's
    readings about their mean (mm / rad), None for a group without two readings of a stop;
    `set_aside`: readings far from the other readings of their stop (`within_stop_errors`),
    not in the mean."""

    stops: int
    rows: int
    per_stop: float
    within: dict
    set_aside: list = field(default_factory=list)  # `outliers.GrossError`s within stops
    # {group: `Trend`}: whether the readings of a stop move with their order (`trend_test`),
    # of the readings as read; `early` (row, column) pairs (0-based) of each stop's first
    # readings left out for it (`settled`), `early_rounds` how many a stop; `trend_after`
    # the test of the readings kept
    trend: dict = field(default_factory=dict)
    early: list = field(default_factory=list)
    early_rounds: int = 0
    trend_after: dict = field(default_factory=dict)
    # (N, 6) the readings of each column merged into each row (1 where a row was read once,
    # 0 where not read or merged into another row)
    counts: np.ndarray | None = field(default=None, repr=False, compare=False)
    # where the stops were read a different number of times and weighted by it
    # (`weigh_stops`): {group: (σ_r, fewest, most readings a stop)} (mm / rad), the table's
    # repeatability the weights were made with
    weighted: dict = field(default_factory=dict)
    # the median rows a stop over every stop with readings (those read once too): the stop
    # whose mean the fit's σ is of (`weigh_stops`, `repeatability`); `per_stop` where None
    typical: float | None = None

    @property
    def reference(self) -> float:
        """The readings of the stop whose mean the fit's σ is of: the median a stop."""
        return self.per_stop if self.typical is None else self.typical

    def repeatability(self, sigma_mean: float, within: float) -> float:
        """The table's repeatability at a stop, √(σ_mean² − σ_within² / k) (0 where the stop
        means scatter less than their readings' noise allows), from the stop means' σ about
        the model and the scatter within stops, k = `reference` readings a stop."""
        return float(np.sqrt(max(sigma_mean**2 - within**2 / self.reference, 0.0)))

    def words(self, sigma: dict | None = None) -> str:
        """In words; with `sigma` {group: σ of a stop's mean about the fitted model}, the
        table's repeatability at a stop: √(σ² − σ_within² / k), k readings a stop."""
        text = (
            f"{self.stops} stop(s) read more than once ({self.rows} rows, "
            f"{self.per_stop:g} a stop: the same command in consecutive rows): each fitted "
            "once, at the mean of its readings (they share the table's error at that stop)"
        )
        parts = []
        for g, (s, dof) in self.within.items():
            if s is None:
                continue
            unit, f = _shown(g)
            part = f"{g} {s * f:.3g} {unit} (dof {dof})"
            if sigma and g in sigma and np.isfinite(sigma[g]):
                rep = self.repeatability(sigma[g], s) * f
                part += (
                    f", the stop means about the model {sigma[g] * f:.3g}: the table's "
                    f"repeatability at a stop {rep:.3g} {unit}"
                )
            parts.append(part)
        if parts:
            text += "; the readings of a stop scatter about their mean by " + "; ".join(parts)
        moving = [t.words(g) for g, t in self.trend.items() if t.found]
        if moving:
            found = {n for t in self.trend.values() for n in t.found}
            text += (
                ". The readings of a stop move with their order ("
                + "; ".join(moving)
                + "): a stop's mean then depends on when it was read"
            )
            if self.early_rounds:
                after = [f"{g} p = {t.varying[2]:.2g}" for g, t in self.trend_after.items()]
                rows = len({r for r, _ in self.early})
                pairs = any(t.columns for t in self.trend.values())
                text += (
                    f"; the first {self.early_rounds} reading(s) of each stop read "
                    f"{'twice' if pairs else 'three times'} "
                    f"or more were left out ({rows} rows), as not settled"
                )
                if any("varying" in t.found for t in self.trend_after.values()):
                    text += ", and the readings kept still settle"  # no stop of 3 left
                elif after:
                    text += (
                        ": the readings kept show no trend that differs from stop to stop ("
                        + ", ".join(after)
                        + f", against {trend_bound(len(after)):.2g})"
                    )
                elif pairs:
                    text += (
                        " (one reading a stop is kept, which cannot be tested again: a table "
                        "that settles slowly still falls short along the move at its second "
                        "reading; read each stop three times or more to test that)"
                    )
                else:
                    text += " (fewer than three readings a stop are kept: not tested again)"
            elif "varying" in found:
                text += (
                    "; take the readings once the table has settled, or leave out a stop's "
                    "first readings"
                )
            if "common" in found:
                text += (
                    "; an instrument that drifts while it reads drifts between the stops too "
                    "(the drift in time that diagnose tests)"
                )
        if self.weighted:
            text += ". The stops were read a different number of times: " + self.weight_words()
        if sigma:
            text += (
                " (a stated σ below is that of a stop's mean, σ / √k: the table's "
                "repeatability is not in it; rows of one command with a move between them, "
                "a pose approached again, put the repeatability in the scatter within)"
            )
        return text

    def weight_words(self) -> str:
        """How the stops read a different number of times were weighted (`weigh_stops`)."""
        parts = []
        for g, (rep, lo, hi) in self.weighted.items():
            unit, f = _shown(g)
            parts.append(f"{g} {lo:g} to {hi:g} readings, σ_r {rep * f:.3g} {unit}")
        return (
            "each stop's mean weighted by its own σ, √(σ_r² + σ_within² / k) for k readings ("
            + "; ".join(parts)
            + "), the table's repeatability σ_r from a first fit that weighted them alike; "
            f"the fit's σ is that of a stop read {self.reference:g} times"
        )

    def as_json(self, sigma: dict | None = None) -> dict:
        """{"stops", "rows", "per_stop", "within_sigma": {group: mm or deg}, and with
        `sigma` "repeatability": {group: mm or deg}}."""
        out = {
            "stops": self.stops,
            "rows": self.rows,
            "per_stop": self.per_stop,
            "within_sigma": {g: _unit(g, s) for g, (s, _) in self.within.items()},
            "trend_within_stops": {g: t.as_json(g) for g, t in self.trend.items()},
            "first_readings_left_out": self.early_rounds,
            "weighted_by_readings": {
                g: {"repeatability": _unit(g, rep), "fewest": lo, "most": hi}
                for g, (rep, lo, hi) in self.weighted.items()
            },
        }
        if sigma:
            out["repeatability"] = {
                g: _unit(g, self.repeatability(sigma[g], s))
                for g, (s, _) in self.within.items()
                if s is not None and g in sigma
            }
        return out


def _shown(group: str) -> tuple:
    """(unit, factor from mm or rad) in which a column group's sizes are written."""
    return ("µm", 1e3) if group == "positions" else ("arcsec", ARCSEC_PER_RAD)


def _unit(group, value):
    if value is None:
        return None
    return float(value) if group == "positions" else float(np.rad2deg(value))


TREND_ALPHA = 0.01
"""Family-wise false-alarm rate of `trend_test` over the column groups it tests."""


def trend_bound(groups: int) -> float:
    """The p-value under which `trend_test` calls a part found: `TREND_ALPHA` shared by the
    two parts of each of the `groups` groups tested."""
    return TREND_ALPHA / (2 * max(groups, 1))


@dataclass(frozen=True)
class Trend:
    """`trend_test` for one column group. The readings' straight line in their order within
    each stop splits into `common`, one slope a column shared by every stop (an instrument
    drifting while it reads), and `varying`, the stops' own slopes about it (a table still
    settling after each move: its direction changes from move to move); each is (F, dof,
    p) against the scatter about the lines (`dof_rest`). `change` / `drift`: the RMS change
    from a stop's first reading to its last, of the stops' lines / of the common one (mm or
    rad); `found`: which of "common", "varying" have p under their share of `TREND_ALPHA`."""

    common: tuple
    varying: tuple
    dof_rest: int
    change: float
    drift: float
    found: tuple
    # `pair_trend_test`'s (stops read twice): the columns whose F the parts (varying,
    # common) are, each part (F, dof, p, rest dof) with p Bonferroni's over the group's
    # columns; None: `trend_test`'s
    columns: tuple | None = None

    def words(self, group: str) -> str:
        unit, f = _shown(group)
        parts = []
        varying = (
            ("along the move into the stop", "RMS from a stop's first reading to its second")
            if self.columns
            else ("differently from stop to stop", "RMS from a stop's first reading to its last")
        )
        for name, size, how, span, cause in (
            ("varying", self.change, *varying, "the table still settling after each move"),
            ("common", self.drift, "the same way at every stop",
             "from the first reading to the last", "the instrument drifting while it reads"),
        ):  # fmt: skip
            if name in self.found:
                F, dof, p, rest = (*getattr(self, name), self.dof_rest)[:4]
                where = ""
                if self.columns:
                    c = self.columns[0 if name == "varying" else 1]
                    where = f"{c}: "
                    p_text = f"p = {p:.2g} over the group's columns"
                else:
                    p_text = f"p = {p:.2g}"
                parts.append(
                    f"{how}, {size * f:.3g} {unit} {span} ({where}F = {F:.3g} on {dof} and "
                    f"{rest} dof, {p_text}): {cause}"
                )
        return f"{group}: " + "; ".join(parts)

    def as_json(self, group: str) -> dict:
        def part(t):  # a pair test's part carries its column's rest dof
            return {"F": t[0], "dof": [t[1], (*t, self.dof_rest)[3]], "p_value": t[2]}

        return {
            "found": list(self.found),
            "varying": part(self.varying),
            "common": part(self.common),
            "first_to_last": _unit(group, self.change),
            "common_first_to_last": _unit(group, self.drift),
            "test": "pairs along the move" if self.columns else "lines in reading order",
        }


PAIR_MIN_DOF = 10
"""Rest degrees of freedom a column needs for `pair_trend_test` (its stops read twice
beyond the test's 7 terms)."""


def stop_moves(data, stop) -> np.ndarray:
    """(S, 6) the commanded move into each stop (`stop_index`) as the pair test's terms:
    its translation and its rotation each a unit vector (0 where that part did not move);
    NaN for the first stop of each session (the move into it is unknown: the table may
    have been homed in between)."""
    cmd = np.asarray(data.cmd_pose, float)
    first = np.searchsorted(stop, np.arange(stop.max() + 1))  # each stop's first row
    c, session = cmd[first], np.asarray(data.session)[first]
    m = np.full(c.shape, np.nan)
    m[1:] = c[1:] - c[:-1]
    m[np.r_[True, session[1:] != session[:-1]]] = np.nan
    out = np.zeros_like(m)
    for part, tiny in ((slice(0, 3), 1e-6), (slice(3, 6), 1e-9)):  # translation, rotation
        norm = np.linalg.norm(m[:, part], axis=1, keepdims=True)
        out[:, part] = np.where(norm > tiny, m[:, part] / np.where(norm > tiny, norm, 1.0), 0.0)
    out[~np.isfinite(m).all(axis=1)] = np.nan
    return out


def _rss(A, d):
    """(residual sum of squares, rank, coefficients) of the least squares of d on A."""
    if A.shape[1] == 0:
        return float(d @ d), 0, np.zeros(0)
    beta, _, rank, _ = np.linalg.lstsq(A, d, rcond=None)
    e = d - A @ beta
    return float(e @ e), int(rank), beta


def _pair_parts(d, moves):
    """One column's pair test: d (n,) first − second reading of each stop read twice,
    `moves` (n, 6) the move into each. Least squares of d on [1, moves]; each part against
    the full fit's residual: (varying (F, dof, p, rest), common (F, dof, p, rest), change
    (n,) the fitted move part, intercept), or None with fewer than `PAIR_MIN_DOF` rest dof."""
    X = np.column_stack([np.ones(len(d)), moves])
    full, rank, beta = _rss(X, d)
    rest = len(d) - rank
    if rest < PAIR_MIN_DOF or full <= 0:
        return None
    parts = []
    for reduced in (X[:, :1], X[:, 1:]):  # without the move terms, without the intercept
        ss, r, _ = _rss(reduced, d)
        dof = rank - r
        F = ((ss - full) / dof) / (full / rest) if dof > 0 else float("nan")
        parts.append((float(F), dof, float(f_sf(F, dof, rest)) if dof > 0 else 1.0, rest))
    return parts[0], parts[1], moves @ beta[1:], float(beta[0])


def _reading_place(read, stop, stops: int) -> np.ndarray:
    """(N, 6) each reading's place among its stop's readings of its column (0 for the first;
    `read` (N, 6) bool, `stop` (N,) nondecreasing over `stops` stops)."""
    upto = np.cumsum(read, axis=0)
    first = np.searchsorted(stop, np.arange(stops))
    before = np.where(first[:, None] > 0, upto[np.maximum(first - 1, 0)], 0)
    return upto - before[stop] - 1


def pair_trend_test(resid, read, stop, k, moves, groups) -> dict:
    """{group: (varying, common, column of each, change, drift)} for the column `groups`
    of stops read exactly twice (k (S, 6)), which `trend_test`'s lines cannot test (a line
    through two readings leaves no scatter to judge it by). A stop's first reading minus
    its second, per column, is regressed on the move into the stop (`stop_moves`: the unit
    translation and rotation, 6 terms) and an intercept: readings of a table that had not
    settled fall short along the move (**varying**: the move terms, 6 dof, whatever the
    instrument's frame, which only mixes them), an instrument drifting while it reads
    shifts every stop's difference alike (**common**: the intercept). Each part's F
    against the fit's residual is exact for independent normal noise; each column is
    tested on its own (columns of one group may have different σ) and a part's p is
    Bonferroni's over the group's columns. `resid` (N, 6): each reading minus its stop's
    mean; `read` (N, 6); `stop` (N,) nondecreasing; `moves` (S, 6)."""
    from .._errors import POSE_COLUMNS

    place = _reading_place(read, stop, k.shape[0])
    sign = np.where(read & (k[stop] == 2), np.where(place == 0, 1.0, -1.0), 0.0)
    d = np.zeros_like(k)
    np.add.at(d, stop, sign * resid)  # first − second
    known = np.isfinite(moves).all(axis=1)
    out = {}
    for g in groups:
        tests = {}
        for c in range(6)[GROUPS[g]]:  # a group's three columns
            t = (k[:, c] == 2) & known
            got = _pair_parts(d[t, c], moves[t]) if t.sum() > 7 else None
            if got is not None:
                tests[c] = got
        if not tests:
            continue
        m = len(tests)
        best = [min(tests, key=lambda c, i=i: tests[c][i][2]) for i in (0, 1)]
        varying, common = (
            (*tests[c][i][:2], min(1.0, m * tests[c][i][2]), tests[c][i][3])
            for i, c in enumerate(best)
        )
        change = float(np.sqrt(np.mean(np.concatenate([t[2] for t in tests.values()]) ** 2)))
        drift = float(np.sqrt(np.mean([t[3] ** 2 for t in tests.values()])))
        names = tuple(POSE_COLUMNS[c] for c in best)
        out[g] = (varying, common, names, change, drift)
    return out


def trend_test(resid, read, stop, k, moves=None) -> dict:
    """{group: `Trend`}: whether the readings of a stop move with the order they were taken
    in (a table that had not settled when the first were taken, an instrument drifting while
    it read), where the readings of a stop should be exchangeable (the table holds still and
    its error at the stop is shared by them all). Per column of a stop read k ≥ 3 times, the
    scatter of its readings about their mean (k − 1 dof) splits into a straight line in the
    reading's order (1 dof) and the rest (k − 2 dof); over a group's stops, the lines split
    into one slope a column shared by every stop and the stops' own slopes about it. Each
    part's mean square over the rest's is F-distributed for readings with independent
    normal noise, whatever their σ and whatever the instrument's frame (each column on its
    own); the two parts of each group share `TREND_ALPHA` equally. A group none of whose
    stops was read three times is tested on its stops read twice, with `moves` (S, 6)
    (`stop_moves`; None: not tested), by `pair_trend_test`; the groups either test covers
    share `TREND_ALPHA`. `resid` (N, 6): each reading minus its stop's mean (0 where not
    read); `read` (N, 6); `stop` (N,) nondecreasing; `k` (S, 6) readings a stop."""
    # each reading's place among its stop's readings of its column, centred: the line's x
    kk = k[stop]
    line_x = np.where(read & (kk >= 3), _reading_place(read, stop, k.shape[0]) - (kk - 1) / 2, 0.0)
    xy, xx, yy = np.zeros_like(k), np.zeros_like(k), np.zeros_like(k)
    np.add.at(xy, stop, line_x * resid)
    np.add.at(xx, stop, line_x * line_x)
    np.add.at(yy, stop, np.where(read & (kk >= 3), resid, 0.0) ** 2)
    tested = k >= 3
    slope = np.divide(xy, xx, out=np.zeros_like(xy), where=xx > 0)
    groups = [g for g, cols in GROUPS.items() if tested[:, cols].any()]
    rest = [g for g in GROUPS if g not in groups]
    pairs = {} if moves is None or not rest else pair_trend_test(resid, read, stop, k, moves, rest)
    alpha = trend_bound(len(groups) + len(pairs))
    out = {}
    for g, (varying, common, names, change, drift) in pairs.items():
        found = tuple(n for n, t in (("varying", varying), ("common", common)) if t[2] < alpha)
        out[g] = Trend(common, varying, common[3], change, drift, found, columns=names)
    for g in groups:
        cols = GROUPS[g]
        t = tested[:, cols]
        lines = float(np.sum((slope * xy)[:, cols][t]))
        rest = float(yy[:, cols][t].sum()) - lines
        d_rest = int(np.sum(k[:, cols][t] - 2))
        # one slope a column: Σ xy / Σ xx over the stops that test it
        sxy = np.where(t, xy[:, cols], 0.0).sum(0)
        sxx = np.where(t, xx[:, cols], 0.0).sum(0)
        ok = sxx > 0
        common = float(np.sum(sxy[ok] ** 2 / sxx[ok]))
        d_common, d_varying = int(ok.sum()), int(t.sum()) - int(ok.sum())
        if d_rest == 0 or rest <= 0:
            continue
        parts = {}
        for name, ss, dof in (("common", common, d_common), ("varying", lines - common, d_varying)):
            F = (ss / dof) / (rest / d_rest) if dof > 0 else float("nan")
            parts[name] = (float(F), dof, float(f_sf(F, dof, d_rest)) if dof > 0 else 1.0)
        span = np.where(t, k[:, cols] - 1, 0)
        pooled = np.divide(sxy, sxx, out=np.zeros_like(sxy), where=ok)
        out[g] = Trend(
            common=parts["common"],
            varying=parts["varying"],
            dof_rest=d_rest,
            change=float(np.sqrt(np.mean((slope[:, cols] * span)[t] ** 2))),
            drift=float(np.sqrt(np.mean((pooled * np.median(span[t])) ** 2))),
            found=tuple(n for n in ("varying", "common") if parts[n][2] < alpha),
        )
    return out


def _first_rows(has, stop) -> np.ndarray:
    """(S,) the first row of each stop with readings (`has` (N,) bool; N for a stop with
    none)."""
    first = np.full(stop.max() + 1, len(stop))
    np.minimum.at(first, stop[has], np.flatnonzero(has))
    return first


def _trend(measured, stop, moves=None):
    """`trend_test` of the readings `measured` (N, 6) in stops `stop` (`moves`: the moves
    into the stops, `stop_moves`)."""
    read, k, dev, total, _ = _about_stop(measured, stop)
    mean = np.divide(total, k, out=np.zeros_like(total), where=k > 0)
    return trend_test(np.where(read, dev - mean[stop], 0.0), read, stop, k, moves)


def settled(data, stop):
    """(data, {group: `Trend`} as read, left out [(row, column)], rounds, {group: `Trend`}
    of the readings kept): while the readings of the stops move with their order differently
    from stop to stop (`Trend.found` "varying": a table that had not settled when the first
    were taken), the first reading of each stop read three times or more is left out, and
    the rest tested again; where the stops were read twice and their pairs show it
    (`pair_trend_test`), the first of each pair (the second cannot be tested again).
    Readings that settle bias a stop's mean along the move into it,
    which a fit takes for an effect that depends on the direction of travel (80 stops read
    4 times, 15 µm short at the first reading: structure, and diagnose added lead_scale to
    the spiral it should have stopped at). A trend the same at every stop (an instrument
    drifting while it reads) is not settling and leaves the readings as they are."""
    measured = np.asarray(data.measured, float)
    moves = stop_moves(data, stop)
    first = _trend(measured, stop, moves)
    trend, early, rounds = first, [], 0
    while any("varying" in t.found for t in trend.values()):
        has = np.isfinite(measured).any(axis=1)
        count = np.bincount(stop[has], minlength=stop.max() + 1)
        pairs = any(t.columns and "varying" in t.found for t in trend.values())
        rows = _first_rows(has, stop)[count >= (2 if pairs else 3)]
        if len(rows) == 0:
            break
        r, c = np.nonzero(np.isfinite(measured[rows]))
        early += list(zip(rows[r].tolist(), c.tolist()))
        measured = measured.copy()
        measured[rows] = np.nan
        rounds += 1
        trend = _trend(measured, stop, moves)
    if not early:
        return data, first, [], 0, first
    from .outliers import without

    return without(data, early), first, early, rounds, trend


def stop_index(data) -> np.ndarray:
    """(N,) the stop of each row: a new stop where the session, the commanded pose or the
    commanded lengths change from the row before."""
    cmd = np.asarray(data.cmd_pose, float)
    if data.cmd_lengths is not None:
        cmd = np.concatenate([cmd, np.asarray(data.cmd_lengths, float)], axis=1)
    session = np.asarray(data.session)
    new = np.ones(len(cmd), bool)
    new[1:] = np.any(cmd[1:] != cmd[:-1], axis=1) | (session[1:] != session[:-1])
    return np.cumsum(new) - 1


def _about_stop(measured, stop):
    """Each reading against a reading of its stop: (read (N, 6) bool, k (S, 6) readings of
    each column a stop, dev (N, 6) the reading minus its stop's reference (angles wrapped;
    0 where not read), total (S, 6) the sum of dev a stop, ref (S, 6) the reference: the
    stop's first row (0 where that row did not read the column))."""
    read = np.isfinite(measured)
    base = np.where(read, measured, 0.0)
    ref = np.zeros((stop.max() + 1, 6))
    ref[stop[::-1]] = base[::-1]  # the last assignment wins: each stop's first row
    dev = np.where(read, wrap_reading_difference(base - ref[stop]), 0.0)
    k, total = np.zeros_like(ref), np.zeros_like(ref)
    np.add.at(k, stop, read.astype(float))
    np.add.at(total, stop, dev)
    return read, k, dev, total, ref


def within_stop_errors(data, stop, alpha=None) -> list:
    """`outliers.GrossError`s: readings far from the other readings of their stop, in stops
    read at least three times (with two, either could be the one). A reading's deviation
    from the mean of the others of its stop, over its noise √(1 + 1/(k − 1)) σ, with σ the
    group's robust scale (1.4826 × the median of those ratios over the group), against the
    family-wise bound of the gross-error screen (`outliers.threshold`); the largest of a
    stop goes first, and the stop is tested again without it (a gross error pulls the
    mean of the others, and with it the deviations of the readings that are fine). The
    readings of a stop share the table's error at it, so this needs no model: it finds a
    glitch in one reading of a stop before the stop's mean takes a sixth of it into the
    fit, and names the row it was in."""
    from .._errors import POSE_COLUMNS
    from .outliers import ALPHA, GrossError, threshold

    alpha = ALPHA if alpha is None else alpha
    measured = np.asarray(data.measured, float)
    found = []
    for _ in range(10):  # rounds: a few glitches in a stop at most
        read, k, dev, total, _ = _about_stop(measured, stop)
        kk = k[stop]
        tested = read & (kk >= 3)
        if not tested.any():
            break
        others = np.divide(total[stop] - dev, kk - 1, out=np.zeros_like(dev), where=kk > 1)
        ratio = np.where(tested, (dev - others) / np.sqrt(1 + 1 / np.maximum(kk - 1, 1)), 0.0)
        z = np.zeros_like(ratio)
        bound = np.full(ratio.shape, np.inf)
        m = int(tested.sum())
        for cols in GROUPS.values():
            cells = np.zeros_like(tested)
            cells[:, cols] = tested[:, cols]
            if not cells.any():
                continue
            scale = 1.4826 * np.median(np.abs(ratio[cells]))
            if scale > 0:
                z[cells] = ratio[cells] / scale
                bound[cells] = threshold(m, alpha, int(cells.sum()))
        over = np.abs(z) - bound
        if not (over > 0).any():
            break
        # the largest of each stop and column beyond its bound, one a stop this round
        new = []
        for s in np.unique(stop[(over > 0).any(axis=1)]):
            rows = np.flatnonzero(stop == s)
            r, c = np.unravel_index(np.argmax(over[rows]), (len(rows), 6))
            r = rows[r]
            new.append(GrossError(int(r) + 1, POSE_COLUMNS[c], np.nan, float(z[r, c])))
            read[r, c] = False
        found += new
        measured = np.where(read, measured, np.nan)
    # each with its whole error: the reading against the mean of its stop's readings kept
    _, k, _, total, ref = _about_stop(measured, stop)
    original = np.asarray(data.measured, float)
    for i, g in enumerate(found):
        r, c = g.row - 1, POSE_COLUMNS.index(g.column)
        d = (
            wrap_reading_difference(original[r] - ref[stop[r]])[c]
            - total[stop[r], c] / k[stop[r], c]
        )
        found[i] = replace(g, residual=float(d if c < 3 else np.rad2deg(d)))
    return sorted(found, key=lambda g: -abs(g.z))


WEIGHT_TOL = 0.02
"""`weigh_stops` leaves the weights alike where the stops' σ differ from the typical stop's
by less than this fraction in RMS over the readings (2 %: a lost cell or a glitch that
leaves one stop of 60 a reading short, 15 % in its σ, does not call for a second fit)."""


def weigh_stops(data, stops: "Stops", groups, sigma, stated):
    """(data with `relative_sigma`, `Stops` with `weighted`) where the stops were read a
    different number of times; None where their σ are within `WEIGHT_TOL` of the typical
    stop's in RMS (a file that read each stop equally often, or all but a few).

    A stop's mean of k readings has variance σ_r² + σ_w² / k: the table's error at the
    stop (its repeatability σ_r, shared by the readings) and the instrument's noise σ_w
    over k. σ_w is the scatter within stops (`Stops.within`, no model needed); σ_r comes
    from a first fit that weighted the stops alike, whose group σ² is then σ_r² plus
    σ_w² times the mean of 1/k over the group's readings (clipped at 0: stops that scatter
    no more than their readings' noise). A stop read once then weighs as much as its one
    reading deserves: fitted alike, it took the screen's bound for a mean of several and
    was set aside as a gross error (60 stops read 1 to 10 times, noise-only data: 3 files
    of 20 lost readings, against the screen's 1 %). The weights are relative to a stop
    read `Stops.reference` times, so the fit's σ is that stop's.

    `groups` (N, 6) int: each reading's noise group (`noise.NoiseModel.groups`, −1 for
    none), `sigma` (G,) the first fit's σ of each group (mm / rad), `stated` (G,) bool:
    groups whose σ the file states (their σ is the stated one, left alone)."""
    counts = np.asarray(stops.counts, float)
    groups = np.asarray(groups)
    shape = np.ones(counts.shape)
    weighted = {}
    for g in np.unique(groups[groups >= 0]):  # noise groups (a few), not readings
        cells = (groups == g) & (counts >= 1)
        if stated[g] or not cells.any():
            continue
        name = "positions" if np.flatnonzero(cells.any(axis=0))[0] < 3 else "angles"
        within = stops.within.get(name, (None, 0))[0]
        if within is None or not np.isfinite(sigma[g]) or within <= 0:
            continue
        k = counts[cells]
        rep2 = max(float(sigma[g]) ** 2 - within**2 * float(np.mean(1.0 / k)), 0.0)
        shape[cells] = np.sqrt((rep2 + within**2 / k) / (rep2 + within**2 / stops.reference))
        lo, hi = float(k.min()), float(k.max())
        if hi > lo and (name not in weighted or weighted[name][2] - weighted[name][1] < hi - lo):
            weighted[name] = (float(np.sqrt(rep2)), lo, hi)
    if np.sqrt(np.mean((shape[counts >= 1] - 1.0) ** 2)) <= WEIGHT_TOL:
        return None
    return replace(data, relative_sigma=shape), replace(stops, weighted=weighted)


def merge_stops(data, screen: bool = True):
    """(data with each stop's readings merged, `Stops` or None where no stop has two rows
    with readings). Readings far from the other readings of their stop are set aside first
    (`within_stop_errors`), then the first readings of stops that had not settled
    (`settled`); neither with `screen=False`. A column's merged reading is the mean
    of the stop's readings of it (angles about the first, wrapped), in the stop's first row
    with readings; its stated σ, where there is one, that of the mean, √(Σσ²) / k; its
    temperature and payload the stop's means. The other rows' readings are set aside."""
    from .outliers import without

    stop = stop_index(data)
    has = np.isfinite(np.asarray(data.measured, float)).any(axis=1)
    if not (np.bincount(stop[has], minlength=stop.max() + 1) > 1).any():
        return data, None
    glitches = within_stop_errors(data, stop) if screen else []
    if glitches:
        data = without(data, glitches)
    read0 = np.isfinite(np.asarray(data.measured, float)).any(axis=1)
    count0 = np.bincount(stop[read0], minlength=stop.max() + 1)  # before settling
    if screen:
        data, trend, early, rounds, kept = settled(data, stop)
    else:
        measured = np.asarray(data.measured, float)
        trend = _trend(measured, stop, stop_moves(data, stop))
        early, rounds, kept = [], 0, {}
    measured = np.asarray(data.measured, float)
    read, k, dev, total, ref = _about_stop(measured, stop)
    has = read.any(axis=1)
    count = np.bincount(stop[has], minlength=stop.max() + 1)
    n = len(stop)
    lead = _first_rows(has, stop)[stop]  # (N,) the carrying row of each row's stop
    mean_dev = np.divide(total, k, out=np.zeros_like(total), where=k > 0)
    carry = np.unique(lead[has])
    merged = measured.copy()
    out_rows = has & (np.arange(n) != lead)
    merged[out_rows] = np.nan
    mean = wrap_reading_difference(ref + mean_dev)  # angles back to [−π, π)
    merged[carry] = np.where(k[stop[carry]] > 0, mean[stop[carry]], np.nan)
    # the scatter about the stop's mean: pure error, per group
    resid = np.where(read, dev - mean_dev[stop], 0.0)
    within = {}
    for g, cols in GROUPS.items():
        dof = int(np.sum(np.maximum(k[:, cols] - 1, 0)))
        ss = float(np.sum(resid[:, cols] ** 2))
        within[g] = (np.sqrt(ss / dof), dof) if dof > 0 else (None, 0)
    aside = np.zeros(measured.shape, bool) if data.aside is None else np.array(data.aside)
    aside[out_rows] |= read[out_rows]
    changes = {"measured": merged, "aside": aside}
    if data.sigma is not None:
        sigma = np.array(data.sigma, float)
        ss = np.zeros_like(total)
        np.add.at(ss, stop, np.where(read, sigma, 0.0) ** 2)
        sig = np.divide(np.sqrt(ss), k, out=np.full_like(ss, np.nan), where=k > 0)
        sigma[carry] = np.where(k[stop[carry]] > 0, sig[stop[carry]], sigma[carry])
        changes["sigma"] = sigma
    for name in ("temperature", "payload"):
        v = getattr(data, name)
        if v is not None:
            v = np.array(v, float)
            sums = np.zeros(stop.max() + 1)
            cnt = np.zeros(stop.max() + 1)
            ok = has & np.isfinite(v)
            np.add.at(sums, stop[ok], v[ok])
            np.add.at(cnt, stop[ok], 1.0)
            v[carry] = np.where(
                cnt[stop[carry]] > 0, sums[stop[carry]] / np.maximum(cnt[stop[carry]], 1), v[carry]
            )
            changes[name] = v
    counts = np.zeros(measured.shape)
    counts[carry] = k[stop[carry]]
    multi = count > 1
    if not multi.any() and not early:  # the glitches left one reading a stop
        return replace(data, **changes), Stops(0, 0, 1.0, within, glitches, counts=counts)
    left = count  # the fit's stop means are of these
    if not multi.any():  # settling left one reading a stop: the stops as read
        count, multi = count0, count0 > 1
    info = Stops(
        stops=int(multi.sum()),
        rows=int(count[multi].sum()),
        per_stop=float(np.median(count[multi])),
        typical=float(np.median(left[left > 0])),
        within=within,
        set_aside=glitches,
        counts=counts,
        trend=trend,
        early=early,
        early_rounds=rounds,
        trend_after=kept,
    )
    return replace(data, **changes), info
