"""The measurement noise: σ stated in the file (or on the command line), or absent, and in
either case estimated from the fit itself, never trusted blindly.

Measured cells fall into groups that share one unknown scale: positions (x, y, z, mm) and
angles (roll, pitch, yaw, rad) of each instrument, an instrument being the set of columns a
row reads (a file that mixes a 6-D tracker and an x-only interferometer has three groups).
Within a group the stated σ (per row) fix the relative weights; absent, the cells of a group
weigh equally.

Variance-component estimation (Förstner 1979; Koch 1999, ch. 3.6): with weighted residuals
e_i and the redundancy numbers r_i = 1 − H_ii of the weighted least-squares fit (H the hat
matrix, Σ r_i = observations − identifiable parameters), the scale of group g is
ŝ_g² = Σ_g e_i² / Σ_g r_i; the weights are divided by ŝ_g and the fit repeated until every
ŝ_g is 1 to 1 %. The estimate's relative standard deviation is 1/√(2 r_g), and with
stated σ the ratio estimated / stated has the 95 % interval ŝ·√(r/χ²_{r, 0.975}) …
ŝ·√(r/χ²_{r, 0.025}) (r = Σ_g r_i); the stated σ is inconsistent with the data when 1 lies
outside it.

A group's parts, its columns in each session, share one σ unless the data say otherwise:
real instruments are seldom isotropic (a laser tracker measures range better than its
transverse directions, a camera lateral better than depth), and a tracker set up anew may be
set up farther away. After each VCE update the parts' own scales are compared by Bartlett's
test (equal variances, χ²(k − 1) with the parts' redundancies as degrees of freedom; robust
scales, see `pool_columns`); where it rejects at `SPLIT_ALPHA`, the group's parts keep their
own scales for the rest of the fit and the report says so. One pooled σ for parts whose
noise differs misweights them: the noisy part's good readings look like gross errors and its
excess like structure (a tracker with z 4× as noisy as x and y, no σ stated: 34 of 900
readings set aside and "unexplained" structure claimed on noise-only data).
"""

from dataclasses import dataclass

import numpy as np

from .. import _params as params
from .._distributions import chi2_ppf, chi2_sf

SPLIT_ALPHA = 1e-3
"""Level of the test that a group's columns share one σ (see the module docstring): below
it the columns are weighted by their own scales. Small, so that data whose columns do share
one σ keep one in all but 1 fit in 1000."""

# starting σ where none is stated (only the relative weight of the two groups matters to
# the first fit; the estimate replaces them): 10 µm, 2 arcsec
DEFAULT_SIGMA = np.array([0.010] * 3 + [np.deg2rad(2.0 / 3600.0)] * 3)

_UNITS = {
    "mm": 1.0,
    "um": 1e-3,
    "µm": 1e-3,
    "rad": 1.0,
    "deg": np.pi / 180.0,
    "arcsec": np.pi / 180.0 / 3600.0,
    "arcmin": np.pi / 180.0 / 60.0,
}


def parse_sigma(text: str) -> dict:
    """`"x=0.01,roll=2arcsec"` -> {column: σ in mm / rad}. A bare number is mm for x, y, z
    and degrees for roll, pitch, yaw (file units); `xyz=` and `angles=` set a whole group.
    Units: mm, um (µm), deg, arcsec, arcmin, rad."""
    out = {}
    for item in filter(None, (t.strip() for t in text.split(","))):
        name, eq, value = item.partition("=")
        name = name.strip()
        cols = {"xyz": params.XYZ, "positions": params.XYZ}.get(name)
        cols = cols or {"angles": params.POSE[3:]}.get(name) or (name,)
        if not eq or any(c not in params.POSE for c in cols):
            raise ValueError(f"--sigma: '{item}' is not COLUMN=VALUE[unit] (columns x..yaw)")
        value = value.strip()
        unit = next((u for u in sorted(_UNITS, key=len, reverse=True) if value.endswith(u)), "")
        try:
            number = float(value[: len(value) - len(unit)] if unit else value)
        except ValueError:
            raise ValueError(f"--sigma: '{item}': '{value}' is not a number with a unit") from None
        if not number > 0:
            raise ValueError(f"--sigma: '{item}': σ must be positive")
        for c in cols:
            angle = params.POSE.index(c) >= 3
            if unit and (unit in ("mm", "um", "µm")) == angle:
                raise ValueError(f"--sigma: '{item}': unit {unit} does not fit column {c}")
            default = np.pi / 180.0 if angle else 1.0
            out[c] = number * (_UNITS[unit] if unit else default)
    return out


@dataclass(frozen=True)
class NoiseModel:
    """Groups of measured cells and their starting σ.

    - `groups` (N, 6) int: group of each cell, −1 where not measured;
    - `names` (G,): "positions", "angles" (with the instrument's columns when a file mixes
      instruments); `columns` (G,) tuple of column indices;
    - `sigma0` (N, 6): σ the weights start from (mm / rad; NaN where not measured);
    - `stated` (G,) bool: σ stated for every cell of the group (file or `sigma=`);
    - `ratio`: {group name: (6 S,) σ of its parts relative to one another}, fixed (a group
      not named: one σ); None: each fit tests whether the data reject one σ per group and
      weights the parts by their own where they do (`pool_columns`);
    - `session` (N,) int: each row's session index; `sessions` (S,): their labels. A part
      of a group is one column in one session, index k = 6 s + c;
    - `filled` (N, 6) bool or None: measured cells the file gave no σ where their column
      states it elsewhere, which took their column's (`_fill_unstated`).
    """

    groups: np.ndarray
    names: tuple
    columns: tuple
    sigma0: np.ndarray
    stated: np.ndarray
    ratio: dict | None = None
    session: np.ndarray | None = None
    sessions: tuple = ("1",)
    filled: np.ndarray | None = None

    def parts(self, g: int) -> list[int]:
        """Part indices 6 s + c of group g."""
        return group_parts(self.columns[g], len(self.sessions))


def group_parts(columns, n_sessions: int) -> list[int]:
    """Part indices 6 s + c of a group reading `columns` in `n_sessions` sessions."""
    return [6 * k + c for k in range(n_sessions) for c in columns]


def report_unit(columns) -> tuple[str, float]:
    """(unit, factor from mm / rad) in which a group of `columns` is reported: µm for
    positions, arcsec for angles."""
    return ("arcsec", np.rad2deg(1.0) * 3600) if columns[0] >= 3 else ("µm", 1e3)


def noise_model(
    measured: np.ndarray,
    sigma: np.ndarray | None,
    override: dict | None = None,
    ratio: dict | None = None,
    session=None,
    sessions=None,
    aside: np.ndarray | None = None,
    relative: np.ndarray | None = None,
):
    """The NoiseModel of a data set: `measured` (N, 6) with NaN for lost cells, the file's
    σ columns `sigma` (N, 6) or None, `override` {column: σ} (mm / rad) from the user;
    `relative` (N, 6) or None: the σ of each reading without a stated σ relative to its
    group's others (`Measurements.relative_sigma`; None: alike);
    `ratio`: None (each fit tests one σ per group), or {group name: (6 S,) relative σ of
    its parts} fixed for every fit (a group not named: one σ); `session` (N,) each row's
    session index, `sessions` their labels (default: one session); `aside` (N, 6) bool or
    None: readings set aside as gross errors (not measured, no group; their rows keep their
    instrument)."""
    mask = np.isfinite(measured)
    n = len(measured)
    stated_cell = np.zeros((n, 6), bool)
    shape = 1.0 if relative is None else np.where(mask, np.asarray(relative, float), 1.0)
    sigma0 = np.where(mask, DEFAULT_SIGMA * shape, np.nan)
    filled = np.zeros((n, 6), bool)
    if sigma is not None:
        ok = mask & np.isfinite(sigma) & (np.asarray(sigma) > 0)
        sigma0 = np.where(ok, sigma, sigma0)
        stated_cell |= ok
        sigma0, filled = _fill_unstated(sigma0, ok, mask, session)
        stated_cell |= filled
    for c, v in (override or {}).items():
        k = params.POSE.index(c)
        sigma0[:, k] = np.where(mask[:, k], v, np.nan)
        stated_cell[:, k] = mask[:, k]
        filled[:, k] = False
    # instruments: the column sets that many rows read; a row with a lost cell belongs to
    # the smallest such set that holds its columns (a lost cell is not another instrument).
    # Rows are grouped by their column set as a 6-bit code: loops run over the (at most 64)
    # distinct sets, never over rows.
    read = mask if aside is None else mask | np.asarray(aside, bool)
    code = read.astype(int) @ (1 << np.arange(6))
    codes, inverse, counts = np.unique(code, return_inverse=True, return_counts=True)
    seen = codes > 0
    frequent = codes[seen & (counts >= max(3, 0.1 * n))]
    if frequent.size == 0 and seen.any():
        frequent = codes[seen][[np.argmax(counts[seen])]]
    bits = np.array([bin(int(f)).count("1") for f in frequent])
    frequent = frequent[np.lexsort((-counts[np.searchsorted(codes, frequent)], bits))]

    def instrument(c: int) -> int:
        return next((int(f) for f in frequent if c & ~int(f) == 0), c)

    assigned = np.array([instrument(int(c)) if c else 0 for c in codes])[inverse]
    vals, first = np.unique(assigned[code > 0], return_index=True)
    order = [int(v) for v in vals[np.argsort(first)]]  # in order of first appearance
    groups = np.full((n, 6), -1)
    names, columns = [], []
    many = len(order) > 1
    for key in order:
        cols_of = [c for c in range(6) if key >> c & 1]
        rows = assigned == key
        instrument_name = (
            f" ({', '.join(params.POSE[c] for c in cols_of)} instrument)" if many else ""
        )
        parts = (
            ("positions", [c for c in cols_of if c < 3]),
            ("angles", [c for c in cols_of if c >= 3]),
        )
        for part, cols in parts:
            g = len(names)
            cells = rows[:, None] & mask & np.isin(np.arange(6), cols)[None, :]
            if not cells.any():
                continue
            groups[cells] = g
            names.append(part + instrument_name)
            columns.append(tuple(cols))
    stated = np.array([bool(stated_cell[groups == g].all()) for g in range(len(names))], dtype=bool)
    session = np.zeros(n, int) if session is None else np.asarray(session, int)
    sessions = ("1",) if sessions is None else tuple(str(x) for x in sessions)
    ratio = None if ratio is None else dict(ratio)
    return NoiseModel(
        groups,
        tuple(names),
        tuple(columns),
        sigma0,
        stated,
        ratio,
        session,
        sessions,
        filled & (groups >= 0),
    )


def _fill_unstated(sigma0, ok, mask, session):
    """A measured cell without a σ (empty, NaN or not positive) where the file states σ for
    other cells of its column takes the median σ stated in its column in its session, or in
    its column where its session states none: in a session one instrument reads a column,
    so the reading is most likely as good as the others (a file mixing instruments in one
    column and session may be wrong there: the report counts the readings filled). A column
    with no σ stated anywhere stays unstated (its group then is: σ is not inferred from
    another column's). Returns (σ, filled (N, 6) bool)."""
    session = np.zeros(len(sigma0), int) if session is None else np.asarray(session, int)
    need = mask & ~ok
    out = np.array(sigma0, float)
    for c in np.flatnonzero(need.any(axis=0) & ok.any(axis=0)):  # columns, not rows
        fill = np.full(len(out), np.median(out[ok[:, c], c]))
        for s in np.unique(session[ok[:, c]]):  # sessions, not rows
            at = session == s
            fill[at] = np.median(out[ok[:, c] & at, c])
        out[:, c] = np.where(need[:, c], fill, out[:, c])
    return out, need & ok.any(axis=0)[None, :]


# estimated / stated σ where the σ columns were written in another unit than the file's
# (mm, degrees): σ in µm in a mm column is stated 1000× too large, so the ratio is 0.001
UNIT_SLIPS = {
    "positions": (("µm", 1e-3), ("metres", 1e3), ("inches", 25.4)),
    "angles": (
        ("arcsec", 1 / 3600),
        ("arcmin", 1 / 60),
        ("radians", np.rad2deg(1.0)),
        ("mrad", np.rad2deg(1.0) / 1e3),
        ("µrad", np.rad2deg(1.0) / 1e6),
    ),
}


def _ratio(x: float) -> str:
    """A ratio of σ for a report: three decimals, or three significant digits far from 1."""
    return f"{x:.3f}" if 0.01 <= x < 1000 else f"{x:.3g}"


def unit_hint(ratio: float, columns) -> str:
    """' (a ratio near 0.001: σ written in µm? The file's σ are in mm)' where the ratio of
    estimated to stated σ is within 30 % of a unit slip (`UNIT_SLIPS`), else ''. A σ stated
    a few times too large or small is a misstatement; a factor of 1000 or 3600 is a unit."""
    kind = "angles" if columns[0] >= 3 else "positions"
    for unit, factor in UNIT_SLIPS[kind]:
        if abs(np.log(ratio / factor)) < np.log(1.3):
            file_unit = "degrees" if kind == "angles" else "mm"
            return (
                f" (a ratio near {factor:.3g}: σ written in {unit}? The file's σ are in "
                f"{file_unit})"
            )
    return ""


def part_label(k: int, sessions: tuple) -> str:
    """'z' for part k = 6 s + c with one session, else 'z (session B)'."""
    col = params.POSE[k % 6]
    return col if len(sessions) == 1 else f"{col} (session {sessions[k // 6]})"


@dataclass(frozen=True)
class NoiseEstimate:
    """The noise a fit found, per group (see the module docstring).

    - `names`, `columns`, `stated` as `NoiseModel`;
    - `scale` (G,): estimated σ / starting σ; `sigma` (G,): the estimated σ (mm / rad; the
      median over the group's cells when stated σ vary by row), `sigma_std` (G,) its
      standard deviation; `stated_sigma` (G,) the stated σ (median; NaN where not stated);
    - `ratio_interval` (G, 2): 95 % interval of estimated / stated σ (NaN where not stated);
      `consistent` (G,): 1 inside it (None where not stated);
    - `redundancy` (G,): Σ r_i, the group's degrees of freedom; `iterations`: fits made;
      `estimated`: False when the stated σ were used as they are (noise="fixed");
    - per part k = 6 s + c (column c in session s; NaN outside the group's parts), all
      (G, 6 S): `column_scale` the part's own σ / starting σ, `column_sigma` and
      `column_sigma_std` its σ (mm / rad) and standard deviation, `column_redundancy` its
      degrees of freedom, `column_interval` (G, 6 S, 2) the 95 % interval of its ratio to
      the stated σ;
    - `split` (G,): the data reject one σ for the group's parts (`SPLIT_ALPHA`), so each
      part was weighted by its own (`scale`, `sigma` are then the pooled values);
      `equal_p` (G,): that test's p-value (NaN for a single part); `sessions` (S,) labels;
    - `filled` (G,): readings the file gave no σ, which took their column's stated σ
      (`NoiseModel.filled`).
    """

    names: tuple
    columns: tuple
    stated: np.ndarray
    scale: np.ndarray
    sigma: np.ndarray
    sigma_std: np.ndarray
    stated_sigma: np.ndarray
    ratio_interval: np.ndarray
    consistent: tuple
    redundancy: np.ndarray
    iterations: int
    estimated: bool
    column_scale: np.ndarray
    column_sigma: np.ndarray
    column_sigma_std: np.ndarray
    column_redundancy: np.ndarray
    column_interval: np.ndarray
    split: np.ndarray
    equal_p: np.ndarray
    sessions: tuple = ("1",)
    filled: tuple = ()

    def filled_words(self, g: int) -> str:
        """'; σ not stated on 1 reading: its column's stated σ taken', or ''."""
        k = self.filled[g] if g < len(self.filled) else 0
        if not k:
            return ""
        return f"; σ not stated on {k} reading{'s' if k > 1 else ''}: its column's stated σ taken"

    def _parts(self, g: int) -> list[int]:
        """Group g's parts that have cells in the fit."""
        parts = group_parts(self.columns[g], len(self.sessions))
        return [k for k in parts if np.isfinite(self.column_sigma[g, k])]

    def lines(self) -> list[str]:
        """Human-readable lines for a report."""
        out = []
        for g, name in enumerate(self.names):
            unit, f = report_unit(self.columns[g])
            s = f"{self.sigma[g] * f:.3g} ± {self.sigma_std[g] * f:.2g} {unit}"
            dof = f"(dof {self.redundancy[g]:.0f})"
            if self.split[g]:
                out.append(self._split_line(g, name, unit, f))
                continue
            if not self.stated[g]:
                out.append(f"noise, {name}: σ estimated from the fit = {s} {dof}; no σ stated")
                continue
            lo, hi = self.ratio_interval[g]
            st = f"{self.stated_sigma[g] * f:.3g} {unit}"
            verdict = (
                "consistent with the data"
                if self.consistent[g]
                else "INCONSISTENT with the data: the stated σ is "
                + ("too small" if lo > 1 else "too large")
                + unit_hint(self.scale[g], self.columns[g])
            )
            use = "" if self.estimated else " (used as stated: noise='fixed')"
            out.append(
                f"noise, {name}: stated σ {st}, data imply {s} {dof}; ratio "
                f"{_ratio(self.scale[g])} (95 % interval {_ratio(lo)}-{_ratio(hi)}): "
                f"{verdict}{use}" + self.filled_words(g)
            )
        return out

    def _split_line(self, g: int, name: str, unit: str, f: float) -> str:
        cols = self._parts(g)
        what = ", ".join(params.POSE[c] for c in self.columns[g])
        if len(self.sessions) > 1:
            what += " in sessions " + ", ".join(self.sessions)
        head = (
            f"noise, {name}: one σ for {what} is rejected by the data "
            f"(p = {self.equal_p[g]:.2g}), each part weighted by its own"
        )
        parts = []
        for c in cols:
            s = (
                f"{part_label(c, self.sessions)} {self.column_sigma[g, c] * f:.3g} ± "
                f"{self.column_sigma_std[g, c] * f:.2g}"
            )
            if self.stated[g]:
                lo, hi = self.column_interval[g, c]
                s += f" (ratio {_ratio(self.column_scale[g, c])}, 95 % {_ratio(lo)}-{_ratio(hi)})"
            parts.append(s)
        dof = ", ".join(f"{self.column_redundancy[g, c]:.0f}" for c in cols)
        body = f"{'; '.join(parts)} {unit} (dof {dof})"
        if not self.stated[g]:
            return f"{head}: σ estimated from the fit {body}; no σ stated"
        verdict = (
            "consistent with the data"
            if self.consistent[g]
            else "INCONSISTENT with the data in "
            + ", ".join(
                part_label(c, self.sessions)
                for c in cols
                if not self.column_interval[g, c, 0] <= 1.0 <= self.column_interval[g, c, 1]
            )
        )
        use = "" if self.estimated else " (used as stated: noise='fixed')"
        st = f"{self.stated_sigma[g] * f:.3g} {unit}"
        return f"{head}: stated σ {st}, data imply {body}: {verdict}{use}" + self.filled_words(g)

    def as_json(self) -> dict:
        return {
            name: {
                "columns": [params.POSE[c] for c in self.columns[g]],
                "sigma": float(self.sigma[g]),
                "sigma_std": float(self.sigma_std[g]),
                "stated_sigma": None if not self.stated[g] else float(self.stated_sigma[g]),
                "ratio": float(self.scale[g]),
                "ratio_interval": None
                if not self.stated[g]
                else [float(x) for x in self.ratio_interval[g]],
                "consistent": self.consistent[g],
                "sigma_filled": self.filled[g] if g < len(self.filled) else 0,
                "units": "rad" if self.columns[g][0] >= 3 else "mm",
                "split": bool(self.split[g]),
                "equal_sigma_p": None if np.isnan(self.equal_p[g]) else float(self.equal_p[g]),
                "column_sigma": {
                    part_label(k, self.sessions): float(self.column_sigma[g, k])
                    for k in self._parts(g)
                },
                "column_ratio": None
                if not self.stated[g]
                else {
                    part_label(k, self.sessions): float(self.column_scale[g, k])
                    for k in self._parts(g)
                },
            }
            for g, name in enumerate(self.names)
        }


def fit_basis(jacobian: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """(M, r) orthonormal basis of the column space of a weighted Jacobian (M, P), rank-
    truncated like the fit's identifiability analysis (columns scaled to unit norm, singular
    values below `tol` × the largest dropped): H = U Uᵀ is the fit's hat matrix."""
    J = np.asarray(jacobian)
    scale = np.linalg.norm(J, axis=0)
    scale[scale == 0] = 1.0
    U, sv, _ = np.linalg.svd(J / scale, full_matrices=False)
    return U[:, sv > tol * sv[0]] if sv.size else U[:, :0]


def redundancy(jacobian: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """Redundancy numbers r_i = 1 − H_ii (M,) of a weighted least-squares fit with weighted
    Jacobian (M, P) (zero rows: observations not used, r = 0 there)."""
    J = np.asarray(jacobian)
    U = fit_basis(J, tol)
    used = np.any(J != 0, axis=1)
    return np.where(used, 1.0 - np.sum(U**2, axis=1), 0.0)


def group_scales(
    residual, red, groups, use_cells, n_groups: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(ŝ_g, r_g): one VCE update per group from weighted residuals and redundancies
    (flattened like `groups`), over the cells in `use_cells`; `n_groups` groups (default:
    the largest label + 1; a group without cells gets ŝ = 1, r = 0)."""
    e = np.asarray(residual).reshape(-1)
    r = np.asarray(red).reshape(-1)
    gflat = np.asarray(groups).reshape(-1)
    u = np.asarray(use_cells).reshape(-1)
    G = n_groups if n_groups is not None else int(gflat.max()) + 1 if gflat.size else 0
    s = np.ones(G)
    rg = np.zeros(G)
    for g in range(G):
        sel = u & (gflat == g)
        rg[g] = r[sel].sum()
        if rg[g] > 0.5:
            s[g] = np.sqrt(np.sum(e[sel] ** 2) / rg[g])
    return s, rg


def column_groups(groups, session=None, n_sessions: int = 1) -> np.ndarray:
    """(N, 6) label g·6S + 6s + c of each cell's (group g, session s, column c) for
    `session` (N,) indices of `n_sessions` sessions (default: one), −1 where not measured:
    the cells of one part of one group."""
    groups = np.asarray(groups)
    s = np.zeros(len(groups), int) if session is None else np.asarray(session, int)
    label = groups * (6 * n_sessions) + 6 * s[:, None] + np.arange(6)
    return np.where(groups >= 0, label, -1)


MIN_SCREEN_CELLS = 30
"""Fewest readings of a part (a column in a session) that get their own robust scale in the
gross-error screen; a part with fewer shares its column's across the sessions."""


def screen_groups(groups, session, n_sessions: int, cells) -> np.ndarray:
    """(N, 6) labels of the robust scales of the gross-error screen: each part (a column
    of a group in a session: a tracker set up anew may be noisier) with at least
    `MIN_SCREEN_CELLS` fitted readings `cells` (N, 6) its own; the others their column's."""
    part = column_groups(groups, session, n_sessions)
    column = column_groups(groups)
    counts = np.bincount(part[np.asarray(cells) & (part >= 0)], minlength=max(part.max(), 0) + 1)
    own = (part >= 0) & (counts[np.maximum(part, 0)] >= MIN_SCREEN_CELLS)
    return np.where(own, part, np.where(column >= 0, part.max() + 1 + column, -1))


QUANTILES = np.array([0.975, 0.025])
"""The χ² quantiles of a σ's 95 % interval (`estimate`): σ̂ √(r / χ²_q(r))."""

MAD_EFFICIENCY = 0.368
"""Asymptotic efficiency of the median absolute deviation as a normal scale estimate: its
log-variance has the spread of a variance on 0.368 × as many degrees of freedom."""


def robust_scales(
    residual, red, groups, use_cells, n_groups: int, min_red: float = 0.1
) -> np.ndarray:
    """(n_groups,) robust scale of each group's standardised residuals e_i / √r_i (1.4826 ×
    their median absolute value; 1 where the group has no cell with r_i > `min_red`): a few
    gross errors do not inflate it."""
    e = np.asarray(residual).reshape(-1)
    r = np.asarray(red).reshape(-1)
    gflat = np.asarray(groups).reshape(-1)
    ok = np.asarray(use_cells).reshape(-1) & (r > min_red) & (gflat >= 0)
    z = np.abs(e[ok]) / np.sqrt(r[ok])
    out = np.ones(n_groups)
    for g in np.unique(gflat[ok]):  # at most 6 per noise group
        out[g] = 1.4826 * np.median(z[gflat[ok] == g])
    return out


def equal_sigma_p(scale, red) -> float:
    """p-value of Bartlett's test that columns with estimated σ scales `scale` (k,) on `red`
    (k,) degrees of freedom share one σ (χ²(k − 1); NaN for k < 2)."""
    v, r = np.asarray(scale, float) ** 2, np.asarray(red, float)
    k = len(v)
    if k < 2:
        return float("nan")
    R = r.sum()
    pooled = np.sum(r * v) / R
    stat = (R * np.log(pooled) - np.sum(r * np.log(v))) / (
        1.0 + (np.sum(1.0 / r) - 1.0 / R) / (3.0 * (k - 1))
    )
    return float(chi2_sf(max(stat, 0.0), k - 1))


def pooled_scales(column_scale, column_red) -> np.ndarray:
    """(G,) √(Σ r_c ŝ_c² / Σ r_c) over each group's columns with r_c > 0.5 (1 where none):
    one scale for columns estimated on their own."""
    s = np.asarray(column_scale, float)
    r = np.where(np.asarray(column_red, float) > 0.5, column_red, 0.0)
    total = r.sum(axis=1)
    sums = np.sum(r * np.where(r > 0, s, 0.0) ** 2, axis=1)
    return np.sqrt(np.where(total > 0, sums / np.where(total > 0, total, 1.0), 1.0))


def equal_sigma_ps(robust, column_red) -> np.ndarray:
    """(G,) `equal_sigma_p` of each group's columns with r_c > 0.5, from their robust
    scales `robust` (G, 6) on `MAD_EFFICIENCY` × their degrees of freedom."""
    r = np.asarray(column_red, float)
    out = np.full(r.shape[0], np.nan)
    for g in range(r.shape[0]):  # groups: at most a few per instrument
        have = r[g] > 0.5
        if have.any():
            out[g] = equal_sigma_p(np.asarray(robust)[g, have], MAD_EFFICIENCY * r[g, have])
    return out


def pool_columns(column_scale, column_red, split, shared, robust):
    """Scales per column of each group, (G, 6) each: the columns' own σ / σ0 `column_scale`
    on `column_red` degrees of freedom (columns outside a group: r ≤ 0.5), and their robust
    counterparts `robust` (`robust_scales`, times the weights' scales). Returns (scales to
    weight by (G, 6), pooled scale (G,), split (G,) bool, p (G,)): a group keeps its columns'
    own scales where `split` (G,) already says so or Bartlett's test on the robust scales
    (on `MAD_EFFICIENCY` × the degrees of freedom) rejects one σ at `SPLIT_ALPHA` (its pooled
    scale is then √(Σ r_c ŝ_c² / Σ r_c)); else all six entries get `shared` (G,), the group's
    scale from all its cells. The robust test keeps a few gross errors from splitting a group
    (the screen finds them; a split would down-weight their column and mask them)."""
    s = np.asarray(column_scale, float)
    have = np.asarray(column_red, float) > 0.5
    p = equal_sigma_ps(robust, column_red)
    split = np.asarray(split, bool) | (p < SPLIT_ALPHA)
    pooled = np.where(split, pooled_scales(s, column_red), np.asarray(shared, float))
    out = np.where(split[:, None] & have, s, pooled[:, None])
    return out, pooled, split, p


def estimate(
    model: NoiseModel,
    scale,
    red_g,
    use_cells,
    estimated: bool,
    column_scale=None,
    column_red=None,
    split=None,
    equal_p=None,
) -> NoiseEstimate:
    """The NoiseEstimate of a finished fit: `scale` (G,) the final ŝ, `red_g` (G,) the groups'
    redundancies, `use_cells` (N, 6) the cells fitted; per part (G, 6 S) `column_scale` and
    `column_red`, `split` and `equal_p` (G,) from `pool_columns` (default: every part at
    its group's scale, none split)."""
    G, S = len(model.names), len(model.sessions)
    K = 6 * S
    if column_scale is None:
        column_scale = np.repeat(np.asarray(scale, float)[:, None], K, axis=1)
        column_red = np.zeros((G, K))
        split, equal_p = np.zeros(G, bool), np.full(G, np.nan)
    in_group = np.zeros((G, K), bool)
    for g in range(G):
        in_group[g, model.parts(g)] = True
    col_sigma = np.full((G, K), np.nan)
    col_interval = np.full((G, K, 2), np.nan)
    session = np.zeros(len(model.groups), int) if model.session is None else model.session
    for g, k in zip(*np.nonzero(in_group)):
        cells = (model.groups == g) & use_cells & (session == k // 6)[:, None]
        cells[:, np.arange(6) != k % 6] = False
        if not cells.any():
            continue
        col_sigma[g, k] = column_scale[g, k] * np.median(model.sigma0[cells])
        if model.stated[g]:
            rk = max(column_red[g, k], 1.0)
            col_interval[g, k] = column_scale[g, k] * np.sqrt(rk / chi2_ppf(QUANTILES, rk))
    col_scale = np.where(in_group, column_scale, np.nan)
    col_red = np.where(in_group, column_red, np.nan)
    sigma = np.zeros(G)
    stated_sigma = np.full(G, np.nan)
    interval = np.full((G, 2), np.nan)
    consistent = []
    for g in range(G):
        cells = (model.groups == g) & use_cells
        base = np.median(model.sigma0[cells]) if cells.any() else np.nan
        sigma[g] = scale[g] * base
        r = max(red_g[g], 1.0)
        if model.stated[g]:
            stated_sigma[g] = base
            interval[g] = scale[g] * np.sqrt(r / chi2_ppf(QUANTILES, r))
            ok = interval[g, 0] <= 1.0 <= interval[g, 1]
            if split[g]:  # each part's own σ against the statement
                lo, hi = col_interval[g, np.isfinite(col_interval[g, :, 0])].T
                ok = bool(np.all((lo <= 1.0) & (1.0 <= hi)))
            consistent.append(bool(ok))
        else:
            consistent.append(None)
    sigma_std = sigma / np.sqrt(2.0 * np.maximum(red_g, 1.0))
    return NoiseEstimate(
        model.names,
        model.columns,
        model.stated,
        np.asarray(scale, float),
        sigma,
        sigma_std,
        stated_sigma,
        interval,
        tuple(consistent),
        np.asarray(red_g, float),
        0,
        estimated,
        col_scale,
        col_sigma,
        col_sigma / np.sqrt(2.0 * np.maximum(col_red, 1.0)),
        col_red,
        col_interval,
        np.asarray(split, bool),
        np.asarray(equal_p, float),
        model.sessions,
        tuple(
            0 if model.filled is None else int((model.filled & (model.groups == g)).sum())
            for g in range(len(model.names))
        ),
    )
