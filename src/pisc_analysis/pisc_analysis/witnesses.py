"""The witness table: what ``pisc_feasibility --csv FILE`` writes, one row a searched draw,
and what a later study reads back (docs/feasibility.md, "The witness table").

The file is a CSV with leading ``# key: value`` lines, then a header row:

    # format: pisc-witnesses/1
    # catch_by_s: 3.0
    # hold_from_s: 6.0
    # run_s: 10.0
    # seed: 1
    # draws: 300
    # searched: 300
    # distribution: thesis-rig
    # distribution_digest: 0123456789abcdef
    # ... (more keys: config, set, current_limit_a, rounds, restarts, ...)
    draw,feasible,how,caught_at_s,...

``draws`` is the N the draws were made for (a draw's values depend on N as well as on the
seed), ``searched`` the number of draws the command searches (fewer than N with
``--only``): the file is rewritten after every draw, and has that many rows once the
run is complete. The columns
``draw`` (0 .. N-1) and ``feasible`` (``True`` or ``False``) are always there; the
drawn values follow under their parameter names.
"""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

__all__ = ["FORMAT", "REQUIRED_COLUMNS", "REQUIRED_KEYS", "WitnessFileError",
           "read_witness_csv", "write_witness_csv"]

FORMAT = "pisc-witnesses/1"
# the header's keys every table has, and how their values are read
REQUIRED_KEYS: dict[str, type] = {
    "format": str, "catch_by_s": float, "hold_from_s": float, "run_s": float, "seed": int,
    "draws": int, "searched": int, "distribution": str, "distribution_digest": str}
REQUIRED_COLUMNS = ("draw", "feasible")
_TEXT_COLUMNS = ("how", "reason")
_BOOL_COLUMNS = ("feasible", "bound")


class WitnessFileError(ValueError):
    """A file that is not a complete witness table; the message names what is wrong."""


def _text(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return " ".join(_text(v) for v in value)
    return str(value)


def write_witness_csv(path: str | os.PathLike, meta: Mapping[str, Any],
                      rows: Sequence[Mapping[str, Any]]) -> None:
    """Write ``meta`` as ``# key: value`` lines (``format`` first) and ``rows`` as CSV.

    The file is replaced whole (written beside it, then renamed), so a reader never sees
    half of it. Raises ValueError if ``meta`` lacks a required key, a value spans lines,
    or a row lacks ``draw`` or ``feasible``."""
    header = {"format": FORMAT, **meta}
    missing = [k for k in REQUIRED_KEYS if k not in header]
    if missing:
        raise ValueError(f"witness table header lacks {', '.join(missing)}")
    if header["format"] != FORMAT:
        raise ValueError(f"format {header['format']!r}: this writer writes {FORMAT!r}")
    out = io.StringIO()
    for key, value in header.items():
        text = _text(value)
        if "\n" in text or "\r" in text or ":" in key or not key.strip():
            raise ValueError(f"header {key!r}: {text!r}: one line, a key without ':'")
        out.write(f"# {key}: {text}\n")
    columns = list(rows[0]) if rows else list(REQUIRED_COLUMNS)
    for name in REQUIRED_COLUMNS:
        if name not in columns:
            raise ValueError(f"witness table rows lack the column {name!r}")
    writer = csv.DictWriter(out, fieldnames=columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    target = Path(path)
    partial = target.with_name(f".{target.name}.partial")
    partial.write_text(out.getvalue())
    os.replace(partial, target)


def _value(column: str, text: str, where: str) -> Any:
    if column in _BOOL_COLUMNS:
        if text not in ("True", "False"):
            raise WitnessFileError(f"{where}: {column} = {text!r}: True or False expected")
        return text == "True"
    if column == "draw":
        try:
            return int(text)
        except ValueError:
            raise WitnessFileError(f"{where}: draw = {text!r}: a draw number expected") from None
    if column in _TEXT_COLUMNS:
        return text
    if text == "":
        return math.nan
    try:
        return float(text)
    except ValueError:
        return text


def read_witness_csv(path: str | os.PathLike) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The header (a dict: the required keys typed as in :data:`REQUIRED_KEYS`, any other
    key as text) and the rows (dicts: ``draw`` int, ``feasible`` and ``bound`` bool,
    ``how`` and ``reason`` text, other columns float where they parse, NaN where empty)
    of a witness table.

    Raises :class:`WitnessFileError` naming what is wrong: no header lines, another
    format, a required key or column missing or unreadable, a row's draw outside
    0 .. draws-1 or repeated, fewer or more rows than ``searched`` (an interrupted run).
    """
    name = str(path)
    lines = Path(path).read_text().splitlines()
    meta: dict[str, Any] = {}
    body = 0  # the first line after the header
    while body < len(lines) and lines[body].startswith("#"):
        key, sep, value = lines[body][1:].partition(":")
        if not sep:
            raise WitnessFileError(f"{name}, line {body + 1}: {lines[body]!r}: "
                                   "'# key: value' expected")
        meta[key.strip()] = value.strip()
        body += 1
    if not meta:
        raise WitnessFileError(f"{name}: no '# key: value' header lines: not a witness "
                               f"table of pisc_feasibility (format {FORMAT})")
    missing = [k for k in REQUIRED_KEYS if k not in meta]
    if missing:
        raise WitnessFileError(f"{name}: the header lacks {', '.join(missing)}")
    if meta["format"] != FORMAT:
        raise WitnessFileError(f"{name}: format {meta['format']!r}, this reader reads "
                               f"{FORMAT!r}")
    for key, kind in REQUIRED_KEYS.items():
        try:
            meta[key] = kind(meta[key])
        except ValueError:
            raise WitnessFileError(f"{name}: {key} = {meta[key]!r}: "
                                   f"{'an integer' if kind is int else 'a number'} "
                                   "expected") from None
    reader = csv.DictReader(lines[body:])
    columns = reader.fieldnames or []
    lacking = [c for c in REQUIRED_COLUMNS if c not in columns]
    if lacking:
        raise WitnessFileError(f"{name}: no column {', '.join(lacking)} (columns: "
                               f"{', '.join(columns) or 'none'})")
    rows: list[dict[str, Any]] = []
    seen: set[int] = set()
    for n, raw in enumerate(reader):
        where = f"{name}, row {n + 1}"
        if None in raw or any(v is None for v in raw.values()):
            raise WitnessFileError(f"{where}: {len(columns)} columns expected")
        row = {c: _value(c, v, where) for c, v in raw.items()}
        if not 0 <= row["draw"] < meta["draws"]:
            raise WitnessFileError(f"{where}: draw {row['draw']} is not among the "
                                   f"{meta['draws']} draws (0 .. {meta['draws'] - 1})")
        if row["draw"] in seen:
            raise WitnessFileError(f"{where}: draw {row['draw']} again")
        seen.add(row["draw"])
        rows.append(row)
    if len(rows) != meta["searched"]:
        raise WitnessFileError(f"{name}: {len(rows)} rows, the header says {meta['searched']} "
                               "draws searched (an interrupted run?)")
    return meta, rows
