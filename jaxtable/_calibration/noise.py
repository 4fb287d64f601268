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
"""

from dataclasses import dataclass

import numpy as np

from .. import _params as params

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
    - `stated` (G,) bool: σ stated for every cell of the group (file or `sigma=`).
    """

    groups: np.ndarray
    names: tuple
    columns: tuple
    sigma0: np.ndarray
    stated: np.ndarray


def noise_model(measured: np.ndarray, sigma: np.ndarray | None, override: dict | None = None):
    """The NoiseModel of a data set: `measured` (N, 6) with NaN for lost cells, the file's
    σ columns `sigma` (N, 6) or None, `override` {column: σ} (mm / rad) from the user."""
    mask = np.isfinite(measured)
    n = len(measured)
    stated_cell = np.zeros((n, 6), bool)
    sigma0 = np.where(mask, DEFAULT_SIGMA, np.nan)
    if sigma is not None:
        ok = mask & np.isfinite(sigma) & (np.asarray(sigma) > 0)
        sigma0 = np.where(ok, sigma, sigma0)
        stated_cell |= ok
    for c, v in (override or {}).items():
        k = params.POSE.index(c)
        sigma0[:, k] = np.where(mask[:, k], v, np.nan)
        stated_cell[:, k] = mask[:, k]
    # instruments: the column sets that many rows read; a row with a lost cell belongs to
    # the smallest such set that holds its columns (a lost cell is not another instrument).
    # Rows are grouped by their column set as a 6-bit code: loops run over the (at most 64)
    # distinct sets, never over rows.
    code = mask.astype(int) @ (1 << np.arange(6))
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
    return NoiseModel(groups, tuple(names), tuple(columns), sigma0, stated)


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
      `estimated`: False when the stated σ were used as they are (noise="fixed").
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

    def lines(self) -> list[str]:
        """Human-readable lines for a report."""
        out = []
        for g, name in enumerate(self.names):
            angle = self.columns[g][0] >= 3
            unit, f = ("arcsec", np.rad2deg(1.0) * 3600) if angle else ("µm", 1e3)
            s = f"{self.sigma[g] * f:.3g} ± {self.sigma_std[g] * f:.2g} {unit}"
            dof = f"(dof {self.redundancy[g]:.0f})"
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
            )
            use = "" if self.estimated else " (used as stated: noise='fixed')"
            out.append(
                f"noise, {name}: stated σ {st}, data imply {s} {dof}; ratio "
                f"{self.scale[g]:.3f} (95 % interval {lo:.3f}-{hi:.3f}): {verdict}{use}"
            )
        return out

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
                "units": "rad" if self.columns[g][0] >= 3 else "mm",
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


def group_scales(residual, red, groups, use_cells) -> tuple[np.ndarray, np.ndarray]:
    """(ŝ_g, r_g): one VCE update per group from weighted residuals and redundancies
    (flattened like `groups`), over the cells in `use_cells`."""
    e = np.asarray(residual).reshape(-1)
    r = np.asarray(red).reshape(-1)
    gflat = np.asarray(groups).reshape(-1)
    u = np.asarray(use_cells).reshape(-1)
    G = int(gflat.max()) + 1 if gflat.size else 0
    s = np.ones(G)
    rg = np.zeros(G)
    for g in range(G):
        sel = u & (gflat == g)
        rg[g] = r[sel].sum()
        if rg[g] > 0.5:
            s[g] = np.sqrt(np.sum(e[sel] ** 2) / rg[g])
    return s, rg


def estimate(model: NoiseModel, scale, red_g, use_cells, estimated: bool) -> NoiseEstimate:
    """The NoiseEstimate of a finished fit: `scale` (G,) the final ŝ, `red_g` (G,) the groups'
    redundancies, `use_cells` (N, 6) the cells fitted."""
    from scipy.stats import chi2

    G = len(model.names)
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
            interval[g] = scale[g] * np.sqrt(r / chi2.ppf([0.975, 0.025], r))
            consistent.append(bool(interval[g, 0] <= 1.0 <= interval[g, 1]))
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
    )
