"""Line-aware numeric CSV parsing: every problem is reported as ``file:line: message``.

Timestamps are parsed as exact integers (EuRoC nanosecond stamps exceed float64's
53-bit mantissa), the other columns as float64.
"""

from __future__ import annotations

from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from vio.errors import DataError


@dataclass(frozen=True)
class NumericTable:
    """Rows of a numeric file: ``t_ns`` (N,) int64, ``values`` (N, C) float64 and the
    1-based file line number of every row (for error messages)."""

    path: Path
    t_ns: np.ndarray
    values: np.ndarray
    lines: np.ndarray


def read_text_lines(path: str | Path) -> list[str]:
    """All lines of a text file, or a ``DataError`` if it is missing or unreadable."""
    path = Path(path)
    if path.is_dir():
        raise DataError(path, "is a folder, not a file")
    if not path.is_file():
        raise DataError(path, "file not found")
    try:
        return path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(path, f"cannot read ({exc})") from None


def parse_seconds_to_ns(text: str) -> int:
    """Decimal seconds string -> integer ns without float rounding ("1403637132.88832")."""
    return int((Decimal(text) * 1_000_000_000).to_integral_value())


def read_numeric(path: str | Path, n_values: int | tuple[int, ...], *, delimiter: str | None = ",",
                 time_in_seconds: bool = False, min_values: int | None = None) -> NumericTable:
    """Parse ``timestamp, v1, ..., vC`` rows; lines starting with ``#`` and blank lines skip.

    ``n_values``: the accepted count(s) of value columns after the timestamp;
    rows shorter than ``max(n_values)`` are NaN-padded if at least ``min_values``.
    ``delimiter=None`` splits on whitespace (TUM files). ``time_in_seconds``:
    the first column is decimal seconds (TUM), converted exactly to ns.
    Raises ``DataError`` on malformed rows and non-finite values.
    """
    accepted = (n_values,) if isinstance(n_values, int) else tuple(n_values)
    width = max(accepted)
    lines = read_text_lines(path)
    t_list: list[int] = []
    rows: list[list[float]] = []
    line_nos: list[int] = []
    first_data = True
    for no, raw in enumerate(lines, start=1):
        s = raw.strip()
        if not s or s.startswith("#") or s.startswith("%"):
            continue
        parts = [p.strip() for p in (s.split(delimiter) if delimiter else s.split())]
        if first_data and not _looks_numeric(parts[0]):
            first_data = False  # an uncommented header line
            continue
        first_data = False
        n = len(parts) - 1
        if n not in accepted and not (min_values is not None and min_values <= n < width):
            raise DataError(path, f"expected {_fmt_counts(accepted)} values after the timestamp, "
                                  f"found {n}", no)
        try:
            t = parse_seconds_to_ns(parts[0]) if time_in_seconds else int(parts[0])
        except (ValueError, InvalidOperation):
            raise DataError(path, f"timestamp {parts[0]!r} is not "
                                  f"{'a decimal number' if time_in_seconds else 'an integer (ns)'}",
                            no) from None
        try:
            vals = [float(p) for p in parts[1:]]
        except ValueError:
            bad = next(p for p in parts[1:] if not _is_float(p))
            raise DataError(path, f"value {bad!r} is not a number", no) from None
        if not all(np.isfinite(vals)):
            raise DataError(path, "non-finite value (NaN or inf)", no)
        vals += [np.nan] * (width - len(vals))
        t_list.append(t)
        rows.append(vals)
        line_nos.append(no)
    if not rows:
        raise DataError(path, "no data rows")
    return NumericTable(path, np.array(t_list, dtype=np.int64), np.array(rows, dtype=np.float64),
                        np.array(line_nos, dtype=np.int64))


def check_increasing(table: NumericTable, what: str = "timestamp") -> None:
    """Raise ``DataError`` at the first row whose stamp does not increase."""
    d = np.diff(table.t_ns)
    bad = np.flatnonzero(d <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        kind = "duplicate" if d[i - 1] == 0 else "decreasing"
        raise DataError(table.path, f"{kind} {what} {table.t_ns[i]} (previous row, line "
                                    f"{table.lines[i - 1]}, has {table.t_ns[i - 1]})",
                        int(table.lines[i]))


def _looks_numeric(s: str) -> bool:
    return _is_float(s)


def _is_float(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def _fmt_counts(counts: tuple[int, ...]) -> str:
    return " or ".join(str(c) for c in counts)
