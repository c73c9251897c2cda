"""Delimited text: tables, header columns, exact decimal stamps."""

from __future__ import annotations

import pathlib
import re
from decimal import Decimal, InvalidOperation

import numpy as np

from jaximu.errors import Fix
from jaximu.io._common import _TIME_UNITS, DataError


def _sniff_delimiter(line):
    for d in (",", "\t", ";"):
        if d in line:
            return d
    return None  # whitespace


def _split(line, delimiter):
    parts = line.split(delimiter) if delimiter else line.split()
    return [p.strip() for p in parts]


def _float(s):
    """``float(s)`` for a decimal number as written in a file: Python's digit separators
    (``1_0``) are refused, not read as 10."""
    if "_" in s:
        raise ValueError(f"not a number: {s!r}")
    return float(s)


def _is_number(s):
    try:
        _float(s)
        return True
    except ValueError:
        return False


def _read_table(path, delimiter=None, comment="#"):
    """``(header, rows, lines)`` of :func:`_read_delimited`."""
    return _read_delimited(path, delimiter, comment)[:3]


def _read_delimited(path, delimiter=None, comment="#"):
    """``(header, rows, lines, delimiter)``: the header fields (or None), the text fields of
    each data row, its 1-based line number, and the delimiter used (``None``: whitespace;
    sniffed from the first data line unless given).

    The header is a first line none of whose fields is a number, or else the last comment
    line before the data with as many fields as the data (ASL files: ``#timestamp [ns],…``).
    Every other non-comment line is data: a text field there is reported when its column is
    used, never dropped as a header.
    """
    path = pathlib.Path(path)
    if path.is_dir():
        raise DataError(f"{path} is a directory, not a file")
    if not path.is_file():
        raise DataError(f"no such file: {path}")
    try:
        text = path.read_text(encoding="utf-8-sig")  # a byte-order mark is not data
    except UnicodeDecodeError:
        raise DataError(f"{path} is not a text file") from None
    numbered = [(k, ln.strip()) for k, ln in enumerate(text.splitlines(), start=1) if ln.strip()]
    if delimiter is None:  # sniffed from the first data line (a comment may hold anything)
        first = next((ln for _, ln in numbered if not ln.startswith(comment)), "")
        delimiter = _sniff_delimiter(first)
    header, comments, rows, lines = None, [], [], []
    for k, line in numbered:
        if line.startswith(comment):
            if not rows:
                comments.append(_split(line.lstrip(comment), delimiter))
            continue
        fields = _split(line, delimiter)
        if not rows and header is None and not any(_is_number(f) for f in fields if f):
            header = fields
            continue
        rows.append(fields)
        lines.append(k)
    if not rows:
        raise DataError(f"{path}: no data rows")
    if header is None:
        header = next((c for c in reversed(comments) if len(c) == len(rows[0])), None)
    return header, rows, np.asarray(lines), delimiter


def _column(header, spec, path):
    if isinstance(spec, (int, np.integer)) and not isinstance(spec, bool):
        if spec < 0:
            raise ValueError(
                f"column indices count from 0 (the first column); got {spec}: "
                "name the column by its index from the left or its header name"
            )
        return int(spec)
    if not isinstance(spec, str):
        raise ValueError(
            f"a column is an index (int ≥ 0) or a header name, got {type(spec).__name__} {spec!r}"
        )
    if header is None:
        raise DataError(f"{path} has no header line: give columns by index, not {spec!r}")
    norm = lambda s: s.split("[")[0].strip().lower()  # noqa: E731  "w_RS_S_x [rad s^-1]"
    for i, h in enumerate(header):
        if h.strip().lower() == spec.lower() or norm(h) == norm(spec):
            return i
    raise DataError(f"{path}: no column named {spec!r}; the header has {header}")


def _to_ns(text, unit_ns, label, unit_option=False, unit="ns"):
    """Exact integer nanoseconds from a decimal string (no float rounding). A stamp that is
    not one (a fraction of a nanosecond, beyond int64) is refused; the repair named is the
    reader's ``time_unit`` where it has one (``unit_option``), else the format's ``unit``."""
    try:
        if "_" in text:  # Decimal reads Python's digit separators: "1_0" would be 10
            raise InvalidOperation
        exact = Decimal(text) * unit_ns
        ns = int(exact.to_integral_value())
    except (InvalidOperation, ValueError, OverflowError):  # text, NaN, inf
        raise DataError(f"{label}: timestamp {text!r} is not a finite number") from None
    problem = None
    if unit_ns == 1 and exact != ns:
        problem = f"{label}: timestamp {text!r} is not a whole number of nanoseconds"
    elif abs(ns) > np.iinfo(np.int64).max:
        problem = f"{label}: timestamp {text!r} is beyond int64 nanoseconds"
    if problem is None:
        return ns
    if unit_option:
        raise DataError(problem, [Fix("time_unit", phrase="check the time unit ({})")], lead="")
    raise DataError(
        f"{problem}; this file's format stamps in {unit}: write its stamps in {unit}, or "
        "read it as a CSV in its time unit (jaximu.io.read_csv(..., time_unit=...); "
        "`--format csv --time-unit UNIT` on the command line)"
    )


def _parse(rows, lines, time_col, value_cols, time_unit, path, unit_option=False):
    """``(stamps [ns] (N,) int64, values (N, len(value_cols)) float64)`` of the text rows;
    ``unit_option``: the caller took ``time_unit`` from its user (a bad stamp's repair)."""
    width = max([time_col, *value_cols]) + 1
    unit_ns = _TIME_UNITS[time_unit]
    stamps = np.empty(len(rows), np.int64)
    values = np.empty((len(rows), len(value_cols)), np.float64)
    for r, (fields, k) in enumerate(zip(rows, lines)):
        if len(fields) < width:
            raise DataError(
                f"{path}, line {k}: expected at least {width} columns, got {len(fields)}"
            )
        stamps[r] = _to_ns(fields[time_col], unit_ns, f"{path}, line {k}", unit_option, time_unit)
        try:
            values[r] = [_float(fields[c]) for c in value_cols]
        except ValueError:
            bad = next(fields[c] for c in value_cols if not _is_number(fields[c]))
            raise DataError(f"{path}, line {k}: {bad!r} is not a number") from None
    return stamps, values


def _parse_tum(rows, lines, path):
    """TUM pose rows ``t tx ty tz qx qy qz qw`` (t in seconds, read exactly to ns) as
    ``(stamps_ns, values)``: ``(M,)`` int64 and ``(M, 7)`` float64 ``[p (3), q (4)]`` with q
    reordered to Hamilton ``[w, x, y, z]``. Every row must have exactly 8 values."""
    for fields, k in zip(rows, lines):
        if len(fields) != 8:
            raise DataError(
                f"{path}, line {k}: a TUM pose has 8 values (t tx ty tz qx qy qz "
                f"qw), got {len(fields)}"
            )
    stamps, values = _parse(rows, lines, 0, range(1, 8), "s", path)
    return stamps, values[:, [0, 1, 2, 6, 3, 4, 5]]


def _check_unit(kind, unit, table):
    if unit not in table:
        raise ValueError(f"unknown {kind} {unit!r}; choose one of {sorted(table)}")
    return table[unit]


def _header_time_unit(header, col):
    """The unit a header states for the time column (``#timestamp [ns]``), or None."""
    if header is None or col >= len(header):
        return None
    m = re.search(r"\[\s*(ns|us|µs|ms|s)\s*\]", str(header[col]))
    return None if m is None else {"µs": "us"}.get(m.group(1), m.group(1))
