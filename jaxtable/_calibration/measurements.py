"""Measurement files (CSV, one row per stop, rows in the order the table moved).

Schema (DESIGN.md): `cmd_x … cmd_yaw` commanded pose (mm / deg, required); `cmd_l1 … cmd_l6`
commanded joint-to-joint lengths (optional); `x, y, z, roll, pitch, yaw` measured pose (any
subset; empty or NaN = not measured); `sigma_<column>` per-row standard deviation (optional);
`temperature` (°C), `payload` (kg), `time` (seconds, a date and time or a time of day:
`clock.py`), `session` (label) optional; a blank session cell continues the session of the
row before it. Unknown columns are kept and
written back unchanged. Angles are degrees in the file and radians in memory.
"""

import csv
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._context import clock_restarts, time_goes_back
from .._errors import POSE_COLUMNS
from .._io import read_delimited
from .._params import pose_from_file, pose_to_file
from .._rotation import (
    ARCSEC_PER_RAD,
    best_rotation,
    euler_matrices,
    rotation_log,
)
from .clock import ClockError, read_clock

CMD = tuple(f"cmd_{c}" for c in POSE_COLUMNS)
CMD_L = tuple(f"cmd_l{i}" for i in range(1, 7))
MEASURED = POSE_COLUMNS
SIGMA = tuple(f"sigma_{c}" for c in POSE_COLUMNS)
OPTIONAL = ("temperature", "payload", "time")


class DataFileError(ValueError):
    """A measurement file is malformed; the message names the row and column."""


@dataclass
class Measurements:
    """Measured stops, in row order. Poses in mm / rad.

    - `cmd_pose` (N, 6) commanded pose; `cmd_lengths` (N, 6) commanded joint-to-joint lengths
      or None (then the controller's inverse kinematics gives them);
    - `measured` (N, 6) measured pose columns, NaN where not measured (a laser
      interferometer along x fills column 0 only);
    - `sigma` (N, 6) standard deviations or None (then the instrument's nominal σ);
    - `temperature`, `payload` (N,) or None; `session` (N,) labels (default all "1");
    - `time` (N,) s or None: the clock of each stop (NaN where not logged); the drift term
      `t` runs over it (`_context.run_time`), else over the row order;
    - `extra`: unknown columns, kept as strings and written back;
    - `aside` (N, 6) bool or None: readings set aside as gross errors (`outliers.without`):
      NaN in `measured`, but read, so that the row keeps its instrument's set of columns;
    - `relative_sigma` (N, 6) or None: the σ of each unstated reading relative to the
      others' (`stops.weigh_stops`: a stop's mean of k readings, √(σ_r² + σ_w²/k), where
      stops were read a different number of times); None: all alike.
    """

    cmd_pose: np.ndarray
    measured: np.ndarray
    cmd_lengths: np.ndarray | None = None
    sigma: np.ndarray | None = None
    temperature: np.ndarray | None = None
    payload: np.ndarray | None = None
    session: np.ndarray | None = None
    extra: dict = field(default_factory=dict)
    aside: np.ndarray | None = None
    time: np.ndarray | None = None
    relative_sigma: np.ndarray | None = None

    def __post_init__(self):
        n = len(self.cmd_pose)
        if self.session is None:
            self.session = np.array(["1"] * n)
        self.session = np.asarray(self.session).astype(str)

    def __len__(self) -> int:
        return len(self.cmd_pose)

    @property
    def measured_columns(self) -> list[str]:
        return [c for k, c in enumerate(MEASURED) if np.any(np.isfinite(self.measured[:, k]))]

    @property
    def sessions(self) -> list[str]:
        """Session labels in order of first appearance."""
        return list(dict.fromkeys(self.session.tolist()))

    @property
    def session_index(self) -> np.ndarray:
        order = {s: k for k, s in enumerate(self.sessions)}
        return np.array([order[s] for s in self.session])

    def clock_words(self) -> str:
        """The clock the drift term `t` runs over, in words for reports: the `time` column
        (its span, and how often it starts again with a new session) or the row order."""
        t = None if self.time is None else np.asarray(self.time, float)
        ok = np.array([]) if t is None else t[np.isfinite(t)]
        if len(ok) < 2 or ok.max() == ok.min():
            return "the row order" + ("" if t is None else " (the `time` column does not move)")
        step = np.diff(ok)
        words = f"the `time` column, {_duration(step[step > 0].sum())} of readings"
        restarts = clock_restarts(t)
        if restarts:
            words += (
                f"; the clock starts again at {restarts} session change(s) (each run on its "
                "own clock): the runs are put end to end, one typical step apart"
            )
        return words

    @property
    def direction(self) -> np.ndarray:
        """(N, 6) ±1: +1 if the leg last moved out (extending), −1 if in, from the row order
        of the commanded lengths (first row +1; a leg that did not move keeps its sign)."""
        from .._context import directions

        if self.cmd_lengths is None:
            raise ValueError("direction needs the commanded lengths (cmd_l1..6)")
        return directions(self.cmd_lengths)

    def subset(self, rows) -> "Measurements":
        rows = np.asarray(rows)

        def take(a):
            return None if a is None else np.asarray(a)[rows]

        return Measurements(
            self.cmd_pose[rows],
            self.measured[rows],
            take(self.cmd_lengths),
            take(self.sigma),
            take(self.temperature),
            take(self.payload),
            take(self.session),
            {k: take(v) for k, v in self.extra.items()},
            take(self.aside),
            take(self.time),
            take(self.relative_sigma),
        )


def _cell(value: str, row: int, col: str, path, required: bool) -> float:
    v = value.strip()
    if v == "" or v.lower() == "nan":
        if required:
            raise DataFileError(f"{path}: row {row}, column '{col}': missing value (required)")
        return math.nan
    try:
        x = float(v)
    except ValueError:
        hint = ""
        try:
            float(v.replace(",", "."))
            hint = " (a decimal comma: write numbers with a decimal point)"
        except ValueError:
            pass
        raise DataFileError(
            f"{path}: row {row}, column '{col}': '{value}' is not a number{hint}"
        ) from None
    if math.isinf(x):
        raise DataFileError(
            f"{path}: row {row}, column '{col}': non-finite value '{value}'"
            + ("" if required else " (an empty cell or NaN marks a value not measured)")
        )
    return x


def _duration(seconds: float) -> str:
    """A span of time in words: "45 s", "12.5 min", "3.1 h", "4.2 days"."""
    for unit, size, limit in (("s", 1, 120), ("min", 60, 7200), ("h", 3600, 172800)):
        if seconds < limit:
            return f"{seconds / size:.3g} {unit}"
    return f"{seconds / 86400:.3g} days"


def _plain_name(h: str) -> str:
    """A header without case, a unit in brackets or after the name ("X [mm]", "Roll (deg)",
    "cmd_x_mm" -> "x", "roll", "cmd_x"), for spotting near misses of the schema's names."""
    name = re.sub(r"\s*[\[(].*[\])]\s*$", "", h.strip().lower())
    return re.sub(r"_(mm|deg|degrees|rad|degc|kg)$", "", name).strip().replace(" ", "_")


def _sessions(cells: list[str]) -> np.ndarray:
    """Session labels with the blank-cell rule: a blank cell continues the session of the
    row before it (a tracker is set up anew only where a label says so); blank cells before
    the first label belong to the first labelled session; an all-blank column is one
    session, "1"."""
    labels = [c.strip() for c in cells]
    first = next((c for c in labels if c), "1")
    out, current = [], first
    for c in labels:
        current = c or current
        out.append(current)
    return np.array(out)


def load_measurements(path) -> Measurements:
    """Read and validate a measurement CSV. Rows are numbered from 1 (the first data row,
    the line after the header). Read as `_io.read_delimited` reads (UTF-8 with or without a
    byte-order mark, any line ending, comma or else semicolon or tab separated, blank lines
    at the end ignored). Refuses, naming row and column: a missing commanded value, a
    non-numeric cell in a known numeric column (with a hint where it is a decimal comma), a
    row that repeats the header (files joined), an infinite value anywhere (a value not
    measured is an empty cell or NaN), a negative σ, a σ of 0 for a measured value, a blank
    line between rows, a row with a different number of cells; and a file with no measured
    column or no commanded-pose columns. Nothing is dropped; unknown columns are kept. An
    empty σ cell beside a measured value is not stated (`noise.noise_model` fills it from
    its column)."""
    path = Path(path)
    header, rows = read_delimited(path, DataFileError, "measurement")
    if not header:
        raise DataFileError(f"{path}: empty file (no header)")
    header = [h.strip() for h in header]
    dup = {h for h in header if header.count(h) > 1}
    if dup:
        raise DataFileError(f"{path}: repeated column(s) {', '.join(sorted(dup))}")
    known = CMD + CMD_L + MEASURED + SIGMA + OPTIONAL + ("session",)
    for h in header:
        name = _plain_name(h)
        if h not in known and name in known and name not in header:
            raise DataFileError(
                f"{path}: column '{h}' looks like '{name}': column names are lower case and "
                "carry no unit (the units are fixed: mm, degrees, °C, kg); rename it, or it "
                "would be kept as an unknown column and not read"
            )
    missing = [c for c in CMD if c not in header]
    if missing:
        raise DataFileError(f"{path}: missing commanded-pose column(s) {', '.join(missing)}")
    if not any(c in header for c in MEASURED):
        raise DataFileError(
            f"{path}: no measured column: need at least one of {', '.join(MEASURED)}"
        )
    if not rows:
        raise DataFileError(f"{path}: no data rows")
    lengths = [c for c in CMD_L if c in header]
    if lengths and len(lengths) != 6:
        raise DataFileError(
            f"{path}: commanded lengths need all of cmd_l1..cmd_l6; found {', '.join(lengths)}"
        )
    col = {h: k for k, h in enumerate(header)}
    n = len(rows)
    for r, row in enumerate(rows, start=1):
        if not row:
            raise DataFileError(f"{path}: row {r} is a blank line (a stop needs its command)")
        if [c.strip() for c in row] == header:
            raise DataFileError(
                f"{path}: row {r} repeats the header (files joined?): delete that line; if "
                "the rows after it were recorded anew (the tracker set up again), label "
                "them with a `session` column"
            )
        if len(row) != len(header):
            raise DataFileError(
                f"{path}: row {r} has {len(row)} cells, the header has {len(header)}"
            )

    def numeric(name, required):
        return np.array([_cell(rows[r][col[name]], r + 1, name, path, required) for r in range(n)])

    def block(names, required):
        return np.stack(
            [numeric(c, required) if c in col else np.full(n, np.nan) for c in names], axis=1
        )

    cmd = pose_from_file(block(CMD, True))
    measured = pose_from_file(block(MEASURED, False))
    cmd_l = block(CMD_L, True) if lengths else None
    sigma = None
    if any(c in col for c in SIGMA):
        sigma = pose_from_file(block(SIGMA, False))
        neg = np.argwhere(sigma < 0)
        if len(neg):
            r, c = neg[0]
            raise DataFileError(f"{path}: row {r + 1}, column '{SIGMA[c]}': negative σ")
        # σ = 0 on a reading would give it infinite weight; where nothing is measured the
        # cell says nothing (a log may write 0 for the columns an instrument does not read)
        zero = np.argwhere((sigma == 0) & np.isfinite(measured))
        if len(zero):
            r, c = zero[0]
            raise DataFileError(
                f"{path}: row {r + 1}, column '{SIGMA[c]}': σ = 0 for a measured value (a "
                "standard deviation must be positive; leave the cell empty where σ is not "
                "known: the column's other σ are taken for it)"
            )
    opt = {c: numeric(c, False) if c in col else None for c in OPTIONAL if c != "time"}
    session = _sessions([rows[r][col["session"]] for r in range(n)]) if "session" in col else None
    opt["time"] = None
    if "time" in col:
        cells = [rows[r][col["time"]] for r in range(n)]
        try:
            opt["time"] = read_clock(cells)
        except ClockError as e:
            raise DataFileError(f"{path}: row {e.row}, column 'time': {e}") from None
        back = time_goes_back(opt["time"], session)
        if back is not None:
            raise DataFileError(
                f"{path}: row {back + 1}, column 'time': the clock goes back to "
                f"'{cells[back].strip()}' within a session (rows are in the order the table "
                "moved; a clock may start again only where the `session` label changes); "
                "or rename the column to keep it unused"
            )
    known = set(CMD + CMD_L + MEASURED + SIGMA + OPTIONAL + ("session",))
    extra = {h: np.array([rows[r][col[h]] for r in range(n)]) for h in header if h not in known}
    return Measurements(
        cmd,
        measured,
        cmd_l,
        sigma,
        opt["temperature"],
        opt["payload"],
        session,
        extra,
        time=opt["time"],
    )


def _turns(angles, order: str = "zyx", signs=(1, 1, 1)) -> np.ndarray:
    """(N − 1, 3) rotation vectors (rad, base frame) of the turns R_next R_prevᵀ between
    consecutive attitudes `angles` (N, 3) (roll, pitch, yaw, rad; composed as
    `euler_matrices(angles, order, signs)`); their norms are the turn angles. numpy, no
    compilation for each number of stops. NaN attitudes give NaN turns."""
    R = euler_matrices(angles, order, signs)
    return rotation_log(R[1:] @ np.swapaxes(R[:-1], -1, -2))


def _moves(data: Measurements) -> dict:
    """Motion between consecutive stops (N − 1 moves), which no instrument frame or target
    changes: {"angles": (measured, commanded, ok), "positions": (...)}, the angle of the
    rotation between the two attitudes (rad) and the distance between the two positions
    (mm); `ok` where both stops are in one session and the kind's three columns are
    measured at both."""
    same = data.session[1:] == data.session[:-1]
    m, c = data.measured, data.cmd_pose
    out = {}
    for kind, sl in (("angles", slice(3, 6)), ("positions", slice(0, 3))):
        ok = same & np.isfinite(m[1:, sl]).all(1) & np.isfinite(m[:-1, sl]).all(1)
        if kind == "angles":
            d_meas = np.linalg.norm(_turns(np.where(np.isfinite(m[:, sl]), m[:, sl], 0.0)), axis=1)
            d_cmd = np.linalg.norm(_turns(c[:, sl]), axis=1)
        else:
            d_meas = np.linalg.norm(m[1:, sl] - m[:-1, sl], axis=1)
            d_cmd = np.linalg.norm(c[1:, sl] - c[:-1, sl], axis=1)
        out[kind] = (np.where(ok, d_meas, np.nan), d_cmd, ok)
    return out


def require_measured(data: Measurements) -> None:
    """Raise DataFileError where no cell of the data is measured (every measured column
    empty or NaN): nothing to fit, predict or diagnose."""
    if not np.isfinite(np.asarray(data.measured)).any():
        raise DataFileError("no measured values in the data (every measured cell is empty)")


def check_units(data: Measurements) -> None:
    """Refuse data whose measured columns move by a different order of magnitude than the
    commands: positions in metres or micrometres, angles in radians, where the file's units
    are mm and degrees (in the measured or the commanded columns). Compared between
    consecutive stops of a session, so the instrument's frame drops out (`_moves`):

    - angles (roll, pitch, yaw all measured): the angle of the rotation between two measured
      attitudes against the commanded one (turns over 0.1°; equal but for noise, whatever
      the frame and the target); the median ratio over at least 5 turns within 20× of 1;
    - positions (x, y, z all measured): the distance between two measured positions against
      the commanded one (moves over 10 mm); a target off the platform's centre adds its
      rotation (up to ~0.3 rad × 500 mm), so the median ratio over at least 5 moves must be
      within 100× of 1 (metres and micrometres are 1000× off).

    Raises DataFileError naming the columns and the ratio."""
    moves = _moves(data)
    checks = (  # kind, columns, least commanded move, allowed ratio, units, suspects
        ("angles", "roll, pitch, yaw", np.deg2rad(0.1), 20.0, "degrees",
         "radians (1/57.3 if the measured ones are, 57.3 if the commanded ones are)"),
        ("positions", "x, y, z", 10.0, 100.0, "mm",
         "metres or micrometres (1/1000 or 1000 if the measured ones are)"),
    )  # fmt: skip
    for kind, cols, least, allowed, unit, suspects in checks:
        d_meas, d_cmd, ok = moves[kind]
        if ok.sum() < 5:
            continue
        use = ok & (d_cmd > least)
        if use.sum() < 5:
            continue
        ratio = float(np.median(d_meas[use] / d_cmd[use]))
        if not 1 / allowed < ratio < allowed:
            raise DataFileError(
                f"the measured {kind} ({cols}) move {ratio:.3g} times as far as the "
                f"commanded ones (median over {int(use.sum())} moves between consecutive "
                f"stops): the file's unit is {unit}; are some in {suspects}?"
            )


# rotation orders `check_angle_convention` tries (the axis rotations' product, left to
# right; the file's first) and senses (roll, pitch, yaw: −1 reversed)
ORDERS = ("zyx", "zxy", "yxz", "yzx", "xzy", "xyz")
SENSES = tuple((a, b, c) for a in (1, -1) for b in (1, -1) for c in (1, -1))  # (1, 1, 1) first


def _convention_words(order: str, signs, undecided: bool = False) -> str:
    """ "Rz(yaw)·Ry(pitch)·Rx(roll) with roll in the other sense"; `undecided`: which of an
    odd number of angles is reversed is not known."""
    names = {"x": "roll", "y": "pitch", "z": "yaw"}
    product = "·".join(f"R{a}({names[a]})" for a in order)
    flipped = [names[a] for a, sg in zip("xyz", signs) if sg < 0]
    if not flipped:
        return product
    if undecided:
        return product + " with one angle, or all three, in the other sense"
    return product + f" with {' and '.join(flipped)} in the other sense"


def _turn_frames(cmd, meas, session, ok):
    """Per session, the rotation F (`best_rotation`) that turns the commanded turn vectors
    `cmd` (K, 3) into the measured ones `meas` (K, 3) over the turns `ok` (K,) of that
    session (`session` (K,) index): ({session: F}, misfit (K,) rad, NaN outside `ok`)."""
    frames, misfit = {}, np.full(len(cmd), np.nan)
    for k in np.unique(session[ok]):  # sessions, not stops
        rows = ok & (session == k)
        if rows.sum() < 3:
            continue
        F, _ = best_rotation(cmd[rows], meas[rows])
        frames[int(k)] = F
        misfit[rows] = np.linalg.norm(meas[rows] - cmd[rows] @ F.T, axis=1)
    return frames, misfit


def _position_frames(data: Measurements) -> dict:
    """Per session with ≥ 10 rows measuring x, y, z: the rotation (`best_rotation`) from
    the commanded positions to the measured ones about their centroids, where they span a
    plane at least (the instrument frame's rotation, up to what a target off the platform's
    centre adds)."""
    out = {}
    idx = data.session_index
    for k in range(len(data.sessions)):  # sessions, not stops
        rows = (idx == k) & np.isfinite(data.measured[:, :3]).all(1)
        if rows.sum() < 10:
            continue
        P, Q = data.cmd_pose[rows, :3], data.measured[rows, :3]
        R, S = best_rotation(P - P.mean(0), Q - Q.mean(0))
        if S[1] > 1e-3 * S[0]:
            out[k] = R
    return out


def _angle_between(A, B) -> float:
    """Angle (deg) of the rotation A Bᵀ."""
    return float(np.degrees(np.linalg.norm(rotation_log(A @ B.T))))


def check_angle_convention(data: Measurements) -> None:
    """Refuse data whose measured angles follow the commands in another attitude convention
    than the file's (R = Rz(yaw) Ry(pitch) Rx(roll), each angle right-handed): an
    instrument that writes another rotation order, an angle measured in the other sense,
    or the inverse attitude. Such angles pass `check_units` (a turn's angle hardly
    changes), and a fit then takes the disagreement for noise ("the stated σ is too small")
    or moves the geometry until the table is not physical.

    Between consecutive stops of a session with all three angles measured, the turn
    R_next R_prevᵀ as a rotation vector: the session's instrument frame F turns the
    commanded turn's vector into the measured one's, and the target's orientation on the
    platform drops out. For each of the six rotation orders with each angle in either
    sense, F is fitted per session to the turns over 0.2° (`best_rotation`), and the median
    misfit taken. Reversing two angles is turning F by 180° (about the third angle's axis),
    so the turns alone cannot tell those senses apart; where the session's positions are
    measured, the convention whose F is closest to the positions' frame (commanded to
    measured positions) is named.

    Refused when at least 10 turns say another convention fits 3× better than the file's
    and the file's misfits by more than 60″ (a table's geometric errors and the effects give
    a few arc-minutes, and no other convention fits them better; at attitudes of a degree
    or less the orders agree to arc-seconds, so only the senses are judged), or when the
    file's convention fits but its F is more than 90° from the positions' frame (two angles
    reversed). Raises DataFileError naming the convention the angles follow."""
    m, c = data.measured[:, 3:], data.cmd_pose[:, 3:]
    idx = data.session_index
    session = idx[1:]
    ok = (idx[1:] == idx[:-1]) & np.isfinite(m[1:]).all(1) & np.isfinite(m[:-1]).all(1)
    if ok.sum() < 10:
        return
    m = np.where(np.isfinite(m), m, 0.0)
    cmd = _turns(c)
    ok &= np.linalg.norm(cmd, axis=1) > np.deg2rad(0.2)
    conventions = [(o, s) for o in ORDERS for s in SENSES]
    fits = [_turn_frames(cmd, _turns(m), session, ok)]  # the file's convention first
    ok &= np.isfinite(fits[0][1])  # turns of sessions with 3 or more
    if ok.sum() < 10:
        return
    positions = _position_frames(data)

    def off(k):  # largest angle (deg) between convention k's frames and the positions'
        frames = fits[k][0]
        return max(
            (_angle_between(frames[s], positions[s]) for s in frames if s in positions),
            default=0.0,
        )

    if np.nanmedian(fits[0][1]) * ARCSEC_PER_RAD <= 60.0 and off(0) <= 90.0:
        return  # the file's convention fits: no other can be judged better
    fits += [_turn_frames(cmd, _turns(m, o, s), session, ok) for o, s in conventions[1:]]
    misfit = np.array([np.nanmedian(f[1]) for f in fits]) * ARCSEC_PER_RAD
    tied = np.flatnonzero(misfit <= 1.5 * misfit.min())
    best = int(min(tied, key=lambda k: (off(k), sum(sg < 0 for sg in conventions[k][1]))))
    if misfit[0] > max(3.0 * misfit[best], 60.0) or (best != 0 and off(0) > 90.0):
        order, signs = conventions[best]
        which = (
            f"median misfit {misfit[best]:.0f}″ over {int(ok.sum())} turns between "
            f"consecutive stops"
            + (f", its frame {off(best):.0f}° from the positions'" if positions else "")
        )
        file_fit = f"{misfit[0]:.0f}″" + (
            f", {off(0):.0f}° from the positions'" if positions else ""
        )
        undecided = not positions and min(signs) < 0
        if order == "xyz" and (undecided or max(signs) < 0):  # R⁻¹ = Rx(−φ) Ry(−θ) Rz(−ψ)
            which += (
                "; reversing all three, that is the inverse: the base's attitude in the "
                "platform's frame"
            )
        raise DataFileError(
            f"the measured angles (roll, pitch, yaw) follow the commands as "
            f"R = {_convention_words(order, signs, undecided)} ({which}), not as the file's "
            f"R = Rz(yaw)·Ry(pitch)·Rx(roll) ({file_fit}): convert the instrument's angles "
            "to the file's convention (DESIGN: yaw, then pitch, then roll, each "
            "right-handed)"
            + (
                "; without measured positions the angles cannot say which (reversing two "
                "more fits them as well)"
                if undecided
                else ""
            )
        )


SHIFTS = (1, -1, 2, -2, 3, -3)  # row shifts `check_alignment` tries


def check_alignment(data: Measurements, nominal=None, lengths=None) -> None:
    """Refuse data whose measured rows do not belong to their commanded rows: a log that
    writes each reading one stop late or early, or a row lost from one of two logs that
    were joined line by line (every row after it shifted). The moves between consecutive
    stops (`_moves`: turn angles, and distances where the commands do not turn, so that a
    target off the platform's centre moves as the centre does) are compared with the
    commanded moves at the same rows and at rows shifted by 1, 2 or 3. With a `nominal`
    table, the commanded lengths (cmd_l columns, which the fit uses) are compared in the
    same way with the table's inverse kinematics of the commanded poses (which label the
    rows and start the forward solve), compensated or not.

    A move agrees with a commanded one within 0.05° + 5 % (turns), 0.1 mm + 1 %
    (distances; the largest leg's change for lengths): a table's geometric errors change a
    turn by arc-seconds to a few arc-minutes, and noise by less. Moves of under 0.2°
    (1 mm) on both sides carry no information and are not counted. Per session, when at
    least 8 moves count and fewer than 90 % agree as the file stands, the rows are refused
    if, from some row on (the session's first, or later: a lost row), at least 90 % of the
    session's moves agree with the rows before at no shift and the rows after at one
    shift, and under 30 % of those after agree unshifted. Data whose moves repeat (a swing
    between two attitudes, equal steps along a line) agree at every shift and are never
    refused.

    `lengths`: `nominal_lengths(nominal, data)` where the caller has them.

    Raises DataFileError naming the session, the row and the shift."""
    session = np.asarray(data.session)
    n = len(session) - 1
    if n < 8:
        return
    same = session[1:] == session[:-1]
    idx = np.arange(n)
    moves = _moves(data)
    cmd_turn = moves["angles"][1]
    pairs = []  # (what moves, names, least move, tolerance, moves, commanded moves, ok)
    for kind, words, least, tol in (
        ("angles", "measured attitudes turn", np.deg2rad(0.2), (np.deg2rad(0.05), 0.05)),
        ("positions", "measured positions move", 1.0, (0.1, 0.01)),
    ):
        d_meas, d_cmd, ok = moves[kind]
        if kind == "positions":  # compared where the commands turn in neither move
            ok = ok & (cmd_turn < np.deg2rad(0.01))
        names = ("measured", "the commanded ones", "commanded")
        pairs.append((words, names, least, tol, d_meas, (d_cmd,), ok))
    if nominal is not None and data.cmd_lengths is not None:
        ik = nominal_lengths(nominal, data) if lengths is None else lengths
        steps = [np.diff(x, axis=0) for x in ik]
        dl = np.diff(np.asarray(data.cmd_lengths, float), axis=0)
        words = "commanded lengths (cmd_l) change"
        names = ("cmd_l", "the inverse kinematics of the commanded poses", "commanded pose")
        pairs.append((words, names, 1.0, (0.1, 0.01), dl, steps, same))
    for words, (mine, theirs, their_row), least, (tol_abs, tol_rel), d_meas, d_cmds, ok in pairs:

        def agree(shift):
            """(counted, agreeing) (n,) for move i against commanded move i + shift (same
            session, both moves within it)."""
            j = idx + shift
            jj = np.clip(j, 0, n - 1)
            valid = ok & ok[jj] & (j >= 0) & (j < n) & (session[1:][jj] == session[1:])
            counted = np.zeros(n, bool)
            good = np.zeros(n, bool)
            for d_cmd in d_cmds:  # agreeing with any of them (compensated or not)
                c = _size(d_cmd[jj])
                counted |= valid & ((np.nan_to_num(_size(d_meas)) > least) | (c > least))
                good |= counted & (_size(d_meas - d_cmd[jj]) <= tol_abs + tol_rel * c)
            return counted, good

        counted0, good0 = agree(0)
        shifted = {k: agree(k) for k in SHIFTS}
        for label in dict.fromkeys(session.tolist()):
            in_s = np.zeros(n, bool)
            in_s[np.flatnonzero(session == label)[:-1]] = True  # moves starting in it
            c0, g0 = counted0 & in_s, good0 & in_s
            if c0.sum() < 8 or g0.sum() >= 0.9 * c0.sum():
                continue
            best = _best_shift(c0, g0, {k: (c & in_s, g & in_s) for k, (c, g) in shifted.items()})
            if best is None:
                continue
            shift, b, k, m, whole = best
            later = "later" if shift > 0 else "earlier"
            # move b joins rows b and b + 1 (0-based); the first of them may still be right
            where = (
                f"session {label!r}" if whole else f"from about row {b + 2} on (session {label!r})"
            )
            raise DataFileError(
                f"{where}: the {words} between consecutive stops as {theirs} "
                f"{abs(shift)} row(s) {later} do ({k} of {m} moves agree at that shift; "
                f"{int(g0.sum())} of {int(c0.sum())} in the session as the file stands): "
                f"{mine} row r belongs to {their_row} row r{shift:+d}; a value logged a stop "
                "late or early, or a row lost from one of two joined logs? Align the rows "
                "and run again"
            )


def nominal_lengths(nominal, data: Measurements) -> list[np.ndarray] | None:
    """The `nominal` table's inverse kinematics of the commanded poses (N, 6) mm, by a
    controller that compensates the spiral term and by one that does not (the file's cmd_l
    may come from either), or None without a table or cmd_l columns: what
    `check_alignment` and `check_commanded` compare the cmd_l columns with (a caller that
    runs both passes them as `lengths`, computed once)."""
    if nominal is None or data.cmd_lengths is None:
        return None
    from .._api import actuator_command

    return [
        np.asarray(actuator_command(nominal, data.cmd_pose, compensated, check=False))
        for compensated in (True, False)
    ]


GROSS_MM = 5.0
"""A commanded pose whose inverse kinematics misses its row's commanded lengths by more than
this (mm, in some leg, beyond that leg's offset common to the file) is refused by
`check_commanded`: a table's geometric errors move a leg by a millimetre or two over the
workspace, the spiral term by tenths."""


def check_commanded(data: Measurements, nominal, lengths=None) -> None:
    """Refuse rows whose commanded pose is not where their commanded lengths (cmd_l columns)
    put the `nominal` table: a typo or a logging glitch in one of them. The fit uses the
    lengths; the pose labels the row and starts the forward solve, which from far enough
    away does not converge. Per row and leg, the lengths minus the table's inverse
    kinematics of the commanded pose (compensated or not, whichever is closer), less the
    leg's median over the file (a controller whose zero lengths differ from the table's
    shifts a leg by the same amount at every row); a row is refused when some leg is off by
    more than `GROSS_MM`.

    `lengths`: `nominal_lengths(nominal, data)` where the caller has them.

    Raises DataFileError naming the rows (numbered from 1, the first data row), the leg and
    how far it is off; no-op without cmd_l columns."""
    if data.cmd_lengths is None or nominal is None:
        return
    cmd_l = np.asarray(data.cmd_lengths, float)
    off = np.full(cmd_l.shape, np.inf)
    for ik in nominal_lengths(nominal, data) if lengths is None else lengths:
        d = cmd_l - ik
        d = d - np.nanmedian(d, axis=0)
        closer = np.nan_to_num(np.abs(d), nan=np.inf).max(1) < np.abs(off).max(1)
        off[closer] = d[closer]
    worst = np.abs(off).max(1)
    bad = np.flatnonzero(~(worst <= GROSS_MM))
    if len(bad) == 0:
        return
    r = int(bad[np.argmax(worst[bad])])
    leg = int(np.argmax(np.abs(off[r])))
    rows = ", ".join(str(b + 1) for b in bad[:10]) + (", ..." if len(bad) > 10 else "")
    raise DataFileError(
        f"row(s) {rows}: the commanded pose (cmd_x..cmd_yaw) is not where the commanded "
        f"lengths (cmd_l1..cmd_l6) put the table: at row {r + 1}, cmd_l{leg + 1} differs "
        f"from the table's inverse kinematics of the commanded pose by {off[r, leg]:+.3f} mm "
        f"(more than {GROSS_MM:g} mm beyond that leg's common offset in this file). A typo "
        "or a glitch in the commanded pose or in the lengths: correct the row or remove it"
    )


def _size(d):
    """Size of each move: |d| for (n,) turns or distances, the largest leg's |change| for
    (n, 6) lengths."""
    return np.abs(d) if d.ndim == 1 else np.abs(d).max(1)


def _best_shift(c0, g0, shifted: dict):
    """The shift and first move b (0-based) that best explain a session's moves: counted
    `c0` and agreeing `g0` (n,) as the file stands, {shift: (counted, agreeing)} shifted;
    the moves before b taken as they stand, those from b on shifted. Returns (shift, b,
    agreeing from b, counted from b, b is the session's first counted move) for the best
    fraction at least 0.9 with at least 5 moves from b, under 30 % of which agree as they
    stand, or None."""

    def before(x):
        return np.concatenate([[0], np.cumsum(x)])[:-1]

    def after(x):
        return np.cumsum(x[::-1])[::-1]

    best = None
    for shift, (c1, g1) in shifted.items():
        total = before(c0) + after(c1)
        frac = (before(g0) + after(g1)) / np.maximum(total, 1)
        real = (
            (after(c1) >= 5)
            & (after(g0) < 0.3 * np.maximum(after(c0), 1))
            & (total >= 8)
            & (frac >= 0.9)
        )
        if real.any():
            b = int(np.argmax(np.where(real, frac, -1.0)))
            if best is None or frac[b] > best[0]:
                best = (frac[b], shift, b, int(after(g1)[b]), int(after(c1)[b]), before(c0)[b] == 0)
    return None if best is None else best[1:]


def save_measurements(m: Measurements, path) -> None:
    """Write `m` as CSV (DESIGN.md schema; angles in degrees; floats written exactly)."""
    cols, data = list(CMD), [pose_to_file(m.cmd_pose)]
    if m.cmd_lengths is not None:
        cols += CMD_L
        data.append(m.cmd_lengths)
    meas = [k for k in range(6) if np.any(np.isfinite(m.measured[:, k]))]
    cols += [MEASURED[k] for k in meas]
    data.append(pose_to_file(m.measured)[:, meas])
    if m.sigma is not None:
        cols += [SIGMA[k] for k in meas]
        data.append(pose_to_file(m.sigma)[:, meas])
    for name in OPTIONAL:
        v = getattr(m, name)
        if v is not None:
            cols.append(name)
            data.append(np.asarray(v, float)[:, None])
    table = np.concatenate(data, axis=1)
    with Path(path).open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(cols + ["session"] + list(m.extra))
        for i in range(len(m)):
            cells = ["" if not np.isfinite(v) else repr(float(v)) for v in table[i]]
            w.writerow(cells + [m.session[i]] + [m.extra[k][i] for k in m.extra])
