"""The fitted model file: what a calibration (or a diagnosis) learned, in one TOML file that
any verb's `--table` reads back and `validate` predicts new data with.

It is a table file (DESIGN.md schema) with three more kinds of table:

    [effects.NAME]                 fitted effect parameters (library and discovered terms)
    [controller]
    zero_lengths = [6 values]      the nominal table's L0 (mm): commanded lengths in new data
                                   convert to actuator extensions s = cmd_l − L0 without the
                                   nominal file
    [instrument]
    target = [x, y, z, roll, pitch, yaw]        target offset on the platform (mm / deg)
    target_sigma = [...]                        its σ (nan: not estimated, inf: undetermined)
    noise = [σx, σy, σz, σroll, σpitch, σyaw]   the noise σ the fit found per measured
    noise_std = [...]                           column (mm / deg; nan: not measured), its σ,
    noise_leverage = [...]                      and the share of the readings the fit took
    readings_per_stop = k                       where the fit's file read its stops k times
    noise_within = [...]                        (consecutive rows, one command): the median
                                                k, and the scatter of a stop's readings
                                                about their mean per column (`noise` is then
                                                that of a stop's mean)
    [instrument.frames."LABEL"]                 one per session label
    pose = [x, y, z, roll, pitch, yaw]          pose of the base frame in the instrument frame
    sigma = [...]                               (a frame the fit let drift: at the session's
                                                last row, where the instrument was last)
"""

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import _params as params
from .._errors import TableFileError
from .._io import (
    effects_from_dict,
    effects_to_toml,
    read_toml,
    table_from_dict,
    table_to_toml,
    toml_value,
)
from .._table import Table, check_table
from .fit import Calibration, hardware_table


@dataclass
class InstrumentFrames:
    """The instrument's nuisance parameters from a fit (mm / rad): the target offset on the
    platform, shared by all sessions, and one frame per session label; σ of each component
    (nan: not estimated, inf: not determined by the data)."""

    target: np.ndarray
    target_sigma: np.ndarray
    frames: dict = field(default_factory=dict)
    frame_sigma: dict = field(default_factory=dict)
    # (6,) the noise σ the fit found per measured column (mm / rad: its group's σ, the
    # median where a column is in several groups) and that σ's standard deviation; NaN for
    # a column not measured, or a file written before they were kept
    noise: np.ndarray = field(default_factory=lambda: np.full(6, np.nan))
    noise_std: np.ndarray = field(default_factory=lambda: np.full(6, np.nan))
    # (6,) the mean leverage H_ii of the column's readings in the fit (the share of them its
    # parameters took): new stops like the fit's are predicted at about σ √(1 + leverage)
    noise_leverage: np.ndarray = field(default_factory=lambda: np.full(6, np.nan))
    # where the fit's file read each stop k times (`stops.merge_stops`): the median k, and
    # the σ of a stop's readings about their mean per column (`noise` is then a mean's:
    # the table's repeatability σ_r² = noise² − noise_within² / k); 1 and NaN otherwise
    readings_per_stop: float = 1.0
    noise_within: np.ndarray = field(default_factory=lambda: np.full(6, np.nan))

    def stop_noise(self, counts) -> np.ndarray:
        """(M, 6) σ of a reading that is the mean of `counts` (M, 6) readings of one stop
        (mm / rad): √(σ_r² + noise_within² / count) where the fit's file read its stops
        several times; `noise` itself otherwise (a mean of several readings is then
        predicted no better than one reading: the split of `noise` into the table's
        repeatability and the instrument's is unknown)."""
        counts = np.maximum(np.asarray(counts, float), 1.0)
        noise = np.broadcast_to(np.asarray(self.noise, float), counts.shape)
        within = np.asarray(self.noise_within, float)
        if not np.isfinite(within).any():
            return noise.copy()
        rep2 = np.maximum(
            np.asarray(self.noise, float) ** 2 - within**2 / self.readings_per_stop, 0
        )
        return np.where(np.isfinite(within), np.sqrt(rep2 + within**2 / counts), noise)


@dataclass
class FittedModel:
    """A fitted model: the table (hardware lead and hand included), its effects (None: the
    table's hardware effects), the instrument frames and target, and the controller's nominal
    zero lengths (None: the table's own)."""

    table: Table
    effects: dict | None = None
    instrument: InstrumentFrames | None = None
    nominal_zero_lengths: np.ndarray | None = None

    @property
    def controller_zero_lengths(self) -> np.ndarray:
        """L0 the controller converts commanded lengths with (mm, (6,))."""
        if self.nominal_zero_lengths is not None:
            return np.asarray(self.nominal_zero_lengths, float)
        return np.asarray(self.table.zero_lengths, float)


def instrument_frames(cal: Calibration, sessions: list[str]) -> InstrumentFrames:
    """The frames and target of a fit, with σ, keyed by the data's session labels (a frame
    that drifted: at its session's last row, `Calibration.frames_at_end`)."""
    std = dict(zip(cal.names, cal.std))

    def sigma(prefix: str, dofs) -> np.ndarray:
        out = np.full(6, np.nan)
        for d in dofs:
            out[d] = std.get(f"{prefix}.{params.POSE[d]}", np.nan)
        return out

    lay = cal.layout
    frames = {lab: cal.frames_at_end()[k] for k, lab in enumerate(sessions)}
    frame_sigma = {lab: sigma(f"frame[{k + 1}]", lay.frame_dofs) for k, lab in enumerate(sessions)}
    noise, noise_std, lev = column_noise(cal)
    k, within = 1.0, np.full(6, np.nan)
    if cal.stops is not None and cal.stops.stops > 0:
        k = float(cal.stops.reference)
        for g, cols in (("positions", slice(0, 3)), ("angles", slice(3, 6))):
            s = cal.stops.within.get(g, (None, 0))[0]
            if s is not None:
                within[cols] = np.where(np.isfinite(noise[cols]), s, np.nan)
    return InstrumentFrames(
        np.asarray(cal.target, float),
        sigma("target", lay.target_dofs),
        frames,
        frame_sigma,
        noise,
        noise_std,
        lev,
        k,
        within,
    )


def column_noise(cal: Calibration) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per measured column (6,) each: the σ the fit found (mm / rad: its noise group's σ,
    the median over the groups where a file's instruments share a column), that σ's
    standard deviation, and the mean leverage 1 − r_i of the column's readings in the fit;
    NaN where no group holds the column or the fit has no noise estimate."""
    est = cal.noise
    noise, std, lev = np.full(6, np.nan), np.full(6, np.nan), np.full(6, np.nan)
    if est is None:
        return noise, std, lev
    for c in range(6):
        groups = [g for g, cols in enumerate(est.columns) if c in cols]
        if groups:
            noise[c] = np.median(np.asarray(est.sigma, float)[groups])
            std[c] = np.median(np.asarray(est.sigma_std, float)[groups])
    if cal.redundancy is not None and cal.weight is not None:
        used = np.asarray(cal.weight) > 0
        r = np.asarray(cal.redundancy, float).reshape(-1, 6)
        n = used.sum(axis=0)
        lev = np.where(n > 0, np.sum(np.where(used, 1 - r, 0), axis=0) / np.maximum(n, 1), np.nan)
        lev = np.where(np.isfinite(noise), lev, np.nan)
    return noise, std, lev


def fitted_model(cal: Calibration, nominal: Table, sessions: list[str]) -> FittedModel:
    """The model file's content for a fit of data with these session labels."""
    return FittedModel(
        hardware_table(cal),
        dict(cal.effects),
        instrument_frames(cal, sessions),
        np.asarray(nominal.zero_lengths, float),
    )


def model_to_toml(model: FittedModel, header: str = "") -> str:
    """TOML text of a fitted model (inverse of `load_fitted_model`)."""
    text = table_to_toml(model.table, header)
    if model.nominal_zero_lengths is not None:
        text += "\n[controller]\n"
        text += f"zero_lengths = {toml_value(model.nominal_zero_lengths)}\n"
    if model.effects:
        text += effects_to_toml(model.effects)
    ins = model.instrument
    if ins is not None:
        text += "\n[instrument]\n"
        text += f"target = {toml_value(params.pose_to_file(ins.target))}\n"
        text += f"target_sigma = {toml_value(params.pose_to_file(ins.target_sigma))}\n"
        if np.isfinite(ins.noise).any():
            text += f"noise = {toml_value(params.pose_to_file(ins.noise))}\n"
            text += f"noise_std = {toml_value(params.pose_to_file(ins.noise_std))}\n"
            text += f"noise_leverage = {toml_value(ins.noise_leverage)}\n"
        if np.isfinite(ins.noise_within).any():
            text += f"readings_per_stop = {toml_value(float(ins.readings_per_stop))}\n"
            text += f"noise_within = {toml_value(params.pose_to_file(ins.noise_within))}\n"
        for label, pose in ins.frames.items():
            key = label.replace("\\", "\\\\").replace('"', '\\"')
            text += f'\n[instrument.frames."{key}"]\n'
            text += f"pose = {toml_value(params.pose_to_file(pose))}\n"
            sig = ins.frame_sigma.get(label, np.full(6, np.nan))
            text += f"sigma = {toml_value(params.pose_to_file(sig))}\n"
    return text


def save_fitted_model(model: FittedModel, path, header: str = "") -> Path:
    """Write `model` as a table file with its `[controller]`, `[effects.NAME]` and
    `[instrument]` tables; `load_fitted_model` (and any `--table`) reads it back."""
    check_table(model.table)
    path = Path(path)
    path.write_text(model_to_toml(model, header))
    return path


def _vector(doc: dict, key: str, where: str) -> np.ndarray:
    try:
        v = np.asarray(doc[key], dtype=float)
    except (KeyError, TypeError, ValueError):
        raise TableFileError(f"{where}: '{key}' must be 6 numbers") from None
    if v.shape != (6,):
        raise TableFileError(f"{where}: '{key}' must be 6 numbers; got shape {v.shape}")
    return v


def load_fitted_model(path) -> FittedModel:
    """Read a fitted model file (or a plain table file: then only the table, and effects if
    it has `[effects.NAME]` tables). Raises TableFileError naming the file and key."""
    path = Path(path)
    where = str(path)
    doc = read_toml(path, TableFileError, "table")
    table = table_from_dict(doc, where)
    effects = effects_from_dict(doc, where) if "effects" in doc else None
    nominal = None
    if "controller" in doc:
        nominal = _vector(doc["controller"], "zero_lengths", f"{where}: [controller]")
    instrument = None
    if "instrument" in doc:
        sec = doc["instrument"]
        w = f"{where}: [instrument]"
        frames, sigmas = {}, {}

        def vec(d, key, w, default):
            return params.pose_from_file(_vector(d, key, w)) if key in d else default

        for label, fr in sec.get("frames", {}).items():
            fw = f'{where}: [instrument.frames."{label}"]'
            frames[str(label)] = vec(fr, "pose", fw, None)
            if frames[str(label)] is None:
                raise TableFileError(f"{fw}: missing 'pose'")
            sigmas[str(label)] = vec(fr, "sigma", fw, np.full(6, np.nan))
        target = vec(sec, "target", w, np.zeros(6))
        tsig = vec(sec, "target_sigma", w, np.full(6, np.nan))
        noise = vec(sec, "noise", w, np.full(6, np.nan))
        noise_std = vec(sec, "noise_std", w, np.full(6, np.nan))
        lev = _vector(sec, "noise_leverage", w) if "noise_leverage" in sec else np.full(6, np.nan)
        if np.any(noise <= 0) or np.any(noise_std < 0) or np.any((lev < 0) | (lev > 1)):
            raise TableFileError(
                f"{w}: 'noise' must be positive, 'noise_std' not negative, 'noise_leverage' "
                "within 0..1"
            )
        within = vec(sec, "noise_within", w, np.full(6, np.nan))
        k = sec.get("readings_per_stop", 1.0)
        if not isinstance(k, (int, float)) or isinstance(k, bool) or not k >= 1:
            raise TableFileError(f"{w}: 'readings_per_stop' must be a number ≥ 1; got {k!r}")
        if np.any(within <= 0):
            raise TableFileError(f"{w}: 'noise_within' must be positive")
        instrument = InstrumentFrames(
            target, tsig, frames, sigmas, noise, noise_std, lev, float(k), within
        )
    return FittedModel(table, effects, instrument, nominal)
