"""The `time` column of a measurement file: the forms a logger writes, read as seconds.

A cell is one of three forms, and every logged cell of a file has the same one:

- a number: seconds on any clock (seconds since the run began, since 1970, ...);
- a date and time, ISO 8601 (`2026-11-28T08:12:28.5`, a space for the T, `/` for the `-`,
  an optional zone `Z`, `+01:00` or `+0100`) or day first with dots (`28.11.2026 08:12:28`):
  seconds since 1970-01-01 00:00 UTC (a reading without a zone is taken as UTC: only the
  differences between readings matter, and they are right unless the log crosses a change
  of daylight-saving time);
- a time of day (`08:12:28`, `8:12`, `08:12:28.25`): seconds since the first day's
  midnight. A reading more than 12 h earlier than the one before it is the next day's (the
  log ran past midnight); a smaller step back is a clock that goes back.

Day-first and month-first dates with slashes (`11/28/2026`) cannot be told apart and are
refused, as are time zones on some cells and not on others. `Measurements.time` holds the
seconds; a saved file writes them as numbers.
"""

import math
import re
from datetime import UTC, datetime, timedelta, timezone

import numpy as np

_HMS = r"(\d{1,2}):(\d{2})(?::(\d{2}(?:[.,]\d*)?))?"
_ZONE = r"\s*(Z|[+-]\d{2}:?\d{2})?"
_ISO = re.compile(r"(\d{4})[-/](\d{1,2})[-/](\d{1,2})(?:[T ]\s*" + _HMS + r")?" + _ZONE)
_DOTTED = re.compile(r"(\d{1,2})\.(\d{1,2})\.(\d{4})(?:[T ]\s*" + _HMS + r")?")
_CLOCK = re.compile(_HMS)
DAY = 86400.0
NAMES = {"number": "number of seconds", "date": "date and time", "clock": "time of day"}

FORMS = (
    "seconds (a number), a date and time (2026-11-28T08:12:28, 28.11.2026 08:12:28) or a "
    "time of day (08:12:28)"
)


class ClockError(ValueError):
    """A `time` cell that is none of the forms, or a column that mixes them; `row` is
    1-based."""

    def __init__(self, row: int, message: str):
        super().__init__(message)
        self.row = row


def _seconds_of_day(h, m, s) -> float:
    h, m, s = int(h), int(m), float((s or "0").replace(",", "."))
    if h > 23 or m > 59 or s >= 61:
        raise ValueError("no such time of day")
    return 3600.0 * h + 60.0 * m + s


def _zone(text: str | None):
    if text is None:
        return None
    if text == "Z":
        return UTC
    sign = -1 if text[0] == "-" else 1
    digits = text[1:].replace(":", "")
    return timezone(sign * timedelta(hours=int(digits[:2]), minutes=int(digits[2:])))


def _form(cell: str):
    """(form, seconds, zoned) of one non-blank cell: form "number", "date" or "clock";
    None where it is none of them (or names no real date or time)."""
    try:
        x = float(cell)
    except ValueError:
        pass
    else:
        return ("number", x, False) if math.isfinite(x) else None
    try:
        if m := _ISO.fullmatch(cell):
            y, mo, d, h, mi, s, zone = m.groups()
            day = datetime(int(y), int(mo), int(d), tzinfo=_zone(zone) or UTC)
            return "date", day.timestamp() + _seconds_of_day(h or 0, mi or 0, s), zone is not None
        if m := _DOTTED.fullmatch(cell):
            d, mo, y, h, mi, s = m.groups()
            day = datetime(int(y), int(mo), int(d), tzinfo=UTC)
            return "date", day.timestamp() + _seconds_of_day(h or 0, mi or 0, s), False
        if m := _CLOCK.fullmatch(cell):
            return "clock", _seconds_of_day(*m.groups()), False
    except ValueError:  # a month 13, a 25th hour
        return None
    return None


def read_clock(cells) -> np.ndarray:
    """(N,) seconds of the `time` cells (str, N; blank or NaN: not logged, NaN). Raises
    ClockError naming the first cell that is none of the forms (`FORMS`), or whose form or
    time-zone statement differs from the first logged cell's."""
    out = np.full(len(cells), np.nan)
    first = None
    for r, raw in enumerate(cells):
        cell = str(raw).strip()
        if cell == "" or cell.lower() == "nan":
            continue
        got = _form(cell)
        if got is None:
            hint = ""
            if _form(cell.replace(",", ".")):
                hint = " (a decimal comma: write numbers with a decimal point)"
            elif re.match(r"\d{1,2}/\d{1,2}/\d{4}", cell):
                hint = " (a date with slashes, day or month first? write it year first)"
            raise ClockError(
                r + 1,
                f"'{raw}' is not a time{hint}: the column holds {FORMS}; rename the column "
                "to keep it unused",
            )
        form, seconds, zoned = got
        if first is None:
            first = (r, form, zoned, cell)
        elif form != first[1]:
            raise ClockError(
                r + 1,
                f"'{raw}' is a {NAMES[form]}, row {first[0] + 1} ('{first[3]}') a "
                f"{NAMES[first[1]]}: one form for the whole column",
            )
        elif zoned != first[2]:
            said = ("states" if zoned else "does not state", "does not" if zoned else "does")
            raise ClockError(
                r + 1,
                f"'{raw}' {said[0]} its time zone, row {first[0] + 1} ('{first[3]}') "
                f"{said[1]}: state it on every cell or on none",
            )
        out[r] = seconds
    if first is not None and first[1] == "clock":
        ok = np.flatnonzero(np.isfinite(out))
        past_midnight = np.concatenate([[0.0], np.diff(out[ok]) < -DAY / 2])
        out[ok] += DAY * np.cumsum(past_midnight)
    return out
