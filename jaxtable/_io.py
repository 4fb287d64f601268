"""Table files (TOML): load, validate, save. Schema: DESIGN.md "Table file"."""

import codecs
import csv
import io
import math
import tomllib
from importlib import resources
from pathlib import Path

import numpy as np

from ._errors import TableFileError
from ._table import Table, check_table

REQUIRED = (
    "home_height",
    "lead",
    "stroke",
    "base_joints",
    "platform_joints",
    "base_axes",
    "platform_axes",
)
OPTIONAL = (
    "name",
    "hand",
    "joint_angle_limit",
    "platform_mass",
    "platform_cog",
    "zero_lengths",
)
# tables a fitted model file adds (jaxtable._calibration.model_file): effect parameters, the
# controller's nominal zero lengths, the instrument's target and frames
SECTIONS = ("effects", "controller", "instrument")


def _array(doc: dict, key: str, shape: tuple[int, ...], where: str) -> np.ndarray:
    value = doc[key]
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TableFileError(
            f"{where}: '{key}' must be numbers of shape {shape}; got {value!r}"
        ) from None
    if arr.shape != shape:
        raise TableFileError(f"{where}: '{key}' must have shape {shape}; got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise TableFileError(f"{where}: '{key}' has non-finite values")
    return arr


def _per_leg(doc: dict, key: str, where: str) -> np.ndarray:
    value = doc[key]
    if isinstance(value, list):
        return _array(doc, key, (6,), where)
    return np.full(6, float(_array(doc, key, (), where)))


def _hand(doc: dict, where: str) -> np.ndarray:
    value = doc.get("hand", "right")
    values = value if isinstance(value, list) else [value] * 6
    if len(values) != 6:
        raise TableFileError(f'{where}: \'hand\' must be "right", "left" or 6 of them')
    out = []
    for i, h in enumerate(values):
        if h not in ("right", "left"):
            raise TableFileError(
                f'{where}: \'hand\' for leg {i + 1} must be "right" or "left"; got {h!r}'
            )
        out.append(1.0 if h == "right" else -1.0)
    return np.array(out)


def table_from_dict(doc: dict, where: str = "table") -> Table:
    """Build and validate a Table from a parsed TOML document (degrees for angles)."""
    missing = [k for k in REQUIRED if k not in doc]
    if missing:
        raise TableFileError(f"{where}: missing key(s) {', '.join(missing)}")
    unknown = [k for k in doc if k not in REQUIRED + OPTIONAL + SECTIONS]
    if unknown:
        raise TableFileError(
            f"{where}: unknown key(s) {', '.join(unknown)}; allowed: "
            f"{', '.join(REQUIRED + OPTIONAL)}"
        )
    kwargs = dict(
        base_joints=_array(doc, "base_joints", (6, 3), where),
        platform_joints=_array(doc, "platform_joints", (6, 3), where),
        base_axes=_array(doc, "base_axes", (6, 3), where),
        platform_axes=_array(doc, "platform_axes", (6, 3), where),
        home_height=_array(doc, "home_height", (), where),
        stroke=_array(doc, "stroke", (2,), where),
        lead=_per_leg(doc, "lead", where),
        hand=_hand(doc, where),
        name=str(doc.get("name", "table")),
    )
    if "zero_lengths" in doc:
        kwargs["zero_lengths"] = _array(doc, "zero_lengths", (6,), where)
    if "joint_angle_limit" in doc:
        kwargs["joint_angle_limit"] = np.deg2rad(_array(doc, "joint_angle_limit", (), where))
    if "platform_mass" in doc:
        kwargs["platform_mass"] = _array(doc, "platform_mass", (), where)
    if "platform_cog" in doc:
        kwargs["platform_cog"] = _array(doc, "platform_cog", (3,), where)
    table = Table(**kwargs)
    try:
        check_table(table)
    except TableFileError as e:
        raise TableFileError(f"{where}: {e}") from None
    return table


# file field -> (effect field, converter file->internal, converter internal->file)
_EFFECT_FILE_FIELDS = {
    "compliance": {"k": ("flex", lambda k: 1.0 / k, lambda f: 1.0 / f)},
}


def effects_from_dict(doc: dict, where: str = "table") -> dict:
    """The `[effects.NAME]` tables of a table file -> {name: effect Module}. Field values are
    a scalar (all legs) or 6 values (rehoming: rows of 6 per later session); compliance is
    written as `k` (N/mm)."""
    from ._effects import MODEL_EFFECTS as EFFECTS

    section = doc.get("effects", {})
    if not isinstance(section, dict):
        raise TableFileError(f"{where}: 'effects' must be a table of [effects.NAME] tables")
    out = {}
    for name, fields in section.items():
        if name not in EFFECTS:
            raise TableFileError(
                f"{where}: unknown effect [effects.{name}]; known: {', '.join(EFFECTS)}"
            )
        cls = EFFECTS[name]
        conv = _EFFECT_FILE_FIELDS.get(name, {})
        allowed = [f for f in cls.fields if f not in {c[0] for c in conv.values()}] + list(conv)
        kwargs = {}
        for key, value in fields.items():
            if key not in allowed:
                raise TableFileError(
                    f"{where}: [effects.{name}] has unknown key '{key}'; allowed: "
                    f"{', '.join(allowed)}"
                )
            try:
                arr = np.asarray(value, dtype=float)
            except (TypeError, ValueError):
                raise TableFileError(f"{where}: [effects.{name}] '{key}' is not numeric") from None
            if key in conv:
                field_name, to_internal, _ = conv[key]
                arr = to_internal(arr)
            else:
                field_name = key
            kwargs[field_name] = arr
        try:
            out[name] = cls(**kwargs)
        except (TypeError, ValueError) as e:
            raise TableFileError(f"{where}: [effects.{name}]: {e}") from None
    return out


def effects_to_toml(effects: dict) -> str:
    """`[effects.NAME]` tables for `effects` (inverse of `effects_from_dict`)."""
    lines = []
    for name in sorted(effects):
        eff = effects[name]
        conv = _EFFECT_FILE_FIELDS.get(name, {})
        lines += ["", f"[effects.{name}]"]
        written = set()
        for key, (field_name, _, to_file) in conv.items():
            lines.append(f"{key} = {toml_value(to_file(np.asarray(getattr(eff, field_name))))}")
            written.add(field_name)
        for f in type(eff).fields:
            if f in written:
                continue
            v = np.asarray(getattr(eff, f))
            if v.ndim == 2:
                lines.append(f"{f} = [" + ", ".join(toml_value(r) for r in v) + "]")
            else:
                lines.append(f"{f} = {toml_value(v)}")
    return "\n".join(lines) + ("\n" if lines else "")


def load_model(path) -> tuple[Table, dict | None]:
    """Read a table file and its `[effects.NAME]` tables: (table, effects), effects None when
    the file has none (then the table's hardware effects apply)."""
    path = Path(path)
    doc = read_toml(path, TableFileError, "table")
    table = table_from_dict(doc, where=str(path))
    return table, (effects_from_dict(doc, str(path)) if "effects" in doc else None)


def read_delimited(
    path, error: type[Exception], kind: str
) -> tuple[list[str] | None, list[list[str]]]:
    """Header and rows of a delimited text file: UTF-8 (a byte-order mark, as spreadsheet
    programs write, is dropped), any line ending; comma-separated, or semicolon- or
    tab-separated where the header line has no comma (spreadsheets in locales with a decimal
    comma). Lines before the header that start with `#` (a logger's preamble: instrument,
    operator, date; in any encoding) and blank lines there are skipped; the header is the
    first other line, or the last comment where the first other line is a row of as many
    cells, a number among them (a header written as a comment, as numpy.savetxt does:
    "# cmd_x,cmd_y,..."). Blank lines at the end of the file are not rows; text in another
    encoding raises `error` naming the row (row 1 = the line after the header) rather than
    being guessed at. A missing file raises `error` naming the `kind` of file."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise error(f"{kind} file not found: {path}") from None
    raw = raw.removeprefix(codecs.BOM_UTF8)
    start, comment = 0, None  # the header line's first byte; the last comment line's
    while (end := raw.find(b"\n", start)) >= 0:
        line = raw[start:end].strip()
        if line and not line.startswith(b"#"):
            break
        comment = start if line else comment
        start = end + 1
    if raw[start:].strip().startswith(b"#"):  # the last line, a comment: no header
        start = len(raw)
    if comment is not None and _header_in_comment(raw[comment:start], raw[start:]):
        # a header written as a comment over the rows (numpy.savetxt's "# cmd_x,...")
        raw = raw[comment:].lstrip().lstrip(b"#").lstrip(b" \t")
    else:
        raw = raw[start:]
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        line = raw.count(b"\n", 0, e.start)
        where = "the header" if line == 0 else f"row {line}"
        raise error(
            f"{path}: {where}: byte 0x{raw[e.start]:02x} is not UTF-8 text "
            "(save the file as UTF-8, e.g. 'CSV UTF-8')"
        ) from None
    delimiter = _delimiter(text.split("\n", 1)[0])
    reader = csv.reader(io.StringIO(text, newline=""), delimiter=delimiter)
    header = next(reader, None)
    rows = list(reader)
    while rows and not any(c.strip() for c in rows[-1]):
        rows.pop()
    return header, rows


def _delimiter(header: str) -> str:
    """The file's delimiter from its header line: a comma, or else a semicolon or a tab."""
    if "," in header:
        return ","
    return next((d for d in (";", "\t") if d in header), ",")


def _header_in_comment(comment: bytes, rest: bytes) -> bool:
    """Whether the comment line is the header of the rows in `rest`: the first row holds a
    number (a header names its columns) and as many cells as the comment without its `#`
    (each split at the comment's delimiter, `_delimiter`)."""
    head = comment.split(b"\n", 1)[0].strip().lstrip(b"#").decode("utf-8", "replace")
    sep = _delimiter(head)

    def cells(line: str) -> list:
        return [c.strip() for c in line.split(sep)]

    def number(c: str) -> bool:
        try:
            float(c)
        except ValueError:
            return False
        return True

    row = cells(rest.split(b"\n", 1)[0].strip().decode("utf-8", "replace"))
    return any(number(c) for c in row if c) and len(cells(head)) == len(row)


def read_toml(path: Path, error: type[Exception], kind: str) -> dict:
    """Parse a TOML file; a missing file or bad TOML raises `error` naming the file."""
    try:
        with Path(path).open("rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise error(f"{kind} file not found: {path}") from None
    except tomllib.TOMLDecodeError as e:
        raise error(f"{path}: not valid TOML: {e}") from None


def load_table(path) -> Table:
    """Read a table file (TOML, DESIGN.md schema) and validate it (its `[effects.NAME]`
    tables are checked too; `load_model` returns them).

    Raises TableFileError naming the file and the offending key/row: a missing or unknown
    key, a wrong shape, a zero or non-unit joint axis, an axis parallel to its leg at home,
    a home pose outside the stroke.
    """
    return load_model(path)[0]


def reference_table() -> Table:
    """The embedded default: a reconstruction of the paper's table (see its TOML header)."""
    ref = resources.files("jaxtable") / "data" / "reference_table.toml"
    with resources.as_file(ref) as path:
        return load_table(path)


def toml_value(x) -> str:
    """A TOML literal for a string, a number (inf, nan included) or a nested list of them."""
    if isinstance(x, str):
        return '"' + x.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(x, (list, tuple)) or (isinstance(x, np.ndarray) and x.ndim > 0):
        return "[" + ", ".join(toml_value(v) for v in x) + "]"
    x = float(x)
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    return repr(x)


def table_to_toml(table: Table, header: str = "") -> str:
    """TOML text of `table` (DESIGN.md schema); floats written exactly (shortest repr)."""
    lead = np.asarray(table.lead)
    hand = ["right" if h > 0 else "left" for h in np.asarray(table.hand)]
    lines = [f"# {h}" if h else "#" for h in header.splitlines()] if header else []
    lines += [
        f"name = {toml_value(table.name)}",
        f"home_height = {toml_value(table.home_height)}",
        f"lead = {toml_value(lead[0] if np.all(lead == lead[0]) else lead)}",
        f"hand = {toml_value(hand[0] if len(set(hand)) == 1 else hand)}",
        f"stroke = {toml_value(np.asarray(table.stroke))}",
    ]
    limit = float(table.joint_angle_limit)
    if math.isfinite(limit):
        lines.append(f"joint_angle_limit = {toml_value(float(f'{np.rad2deg(limit):.12g}'))}")
    lines += [
        f"platform_mass = {toml_value(table.platform_mass)}",
        f"platform_cog = {toml_value(np.asarray(table.platform_cog))}",
        f"zero_lengths = {toml_value(np.asarray(table.zero_lengths))}",
    ]
    for key in ("base_joints", "platform_joints", "base_axes", "platform_axes"):
        rows = np.asarray(getattr(table, key))
        lines.append(f"{key} = [")
        lines += [f"    {toml_value(r)}," for r in rows]
        lines.append("]")
    return "\n".join(lines) + "\n"


def save_table(table: Table, path, header: str = "", effects: dict | None = None) -> None:
    """Write `table` to `path` as TOML (angles in degrees), with `effects` as
    `[effects.NAME]` tables. `load_table` / `load_model` read it back exactly."""
    check_table(table)
    text = table_to_toml(table, header)
    if effects:
        text += effects_to_toml(effects)
    Path(path).write_text(text)
