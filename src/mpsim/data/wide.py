"""Wide CSV: one measured recording per file, one row per sample, one column per signal.

```
time,position,velocity,torque
0.000,-0.0015,0.121,-0.004
0.002,-0.0015,-0.077,-0.532
```

Read as it comes from a lab: the delimiter is sniffed (``,`` ``;`` tab, or runs of spaces; ``;`` with decimal
commas), headers may be quoted or padded with spaces, a trailing delimiter (an empty last column), a UTF-8 byte-order
mark, blank lines and lines starting with ``#`` (comments) are ignored; a ``#`` inside a cell is part of the cell. A
``.gz`` file (``rec.csv.gz``) is read decompressed, and a ``.txt``, ``.dat`` or ``.tsv`` file is read like a ``.csv``.
The time column is `data.time_column` (default ``t``); a file without one needs `data.dt`. A time column of ISO 8601
dates (``2026-01-02 10:00:00.05``) is read as seconds since its first row. Columns holding text are set aside (named
if a model asks for them); a row of text in every column (a repeated header, a footer) is refused, named; empty
cells and NaN/inf are refused when a model uses that column (`mpsim.data.recording.to_recording`). Reading is
vectorised (pandas' C parser): 131 072 rows of four columns take about 0.2 s; the line of each row is found only
when a message names it.
"""

from __future__ import annotations

import csv
import gzip
import io
import re
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from mpsim.data.table import DATA_BYTES, Table, time_grid
from mpsim.errors import DataError
from mpsim.safeload import not_a_regular_file, read_text, size_text

#: lines read to tell the delimiter
SNIFF_LINES = 50
_DELIMITERS = (",", ";", "\t")
#: a comment line: its first character that is not a space is '#'
_COMMENT_LINE = re.compile(r"^[ \t]*#[^\n]*(?:\n|$)", re.M)
#: a decimal comma between digits (a ';' file's rows anywhere in the file, not only its first lines)
_DECIMAL_COMMA = re.compile(r"\d,\d")
#: a number followed by a unit ("0.35s", "12 ms"): a message says to write the number alone
_WITH_UNIT = re.compile(r"^\s*[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?\s*[A-Za-zµ]+\s*$")


def read_wide_csv(path: str | Path, time_column: str | None = "t", dt: float | None = None) -> Table:
    """The columns of the wide CSV `path` (see the module docstring).

    Args:
        path: the file.
        time_column: `data.time_column`, the column holding the times (None: the file has none, use `dt`).
        dt: `data.dt`, the sampling step in seconds for a file without a time column.

    Raises:
        DataError: not a readable UTF-8 text file, no header, an unknown delimiter, rows with more fields than
            the header, duplicate column names, or a time column that is missing, not finite or not increasing.
    """
    path = Path(path)
    text = _text(path)
    lines, comment = _content_lines(text)
    if not lines:
        raise DataError(f"{path}: the file holds no header and no rows (only blank or '#' comment lines).")
    sep, decimal = _sniff(path, lines, text)
    in_comment = _all_numbers(_fields(lines[0][1], sep), decimal)  # np.savetxt writes its header as "# t,q,u"
    names = _header(path, comment if in_comment else lines[0][1], sep)
    if in_comment and (not comment.strip() or len(names) != len(_header(path, lines[0][1], sep))):
        raise DataError(
            f"{path}: line {lines[0][0]} holds numbers, not column names: the file has no header. Add a first line "
            "naming the columns (e.g. t,q,u), separated like the rows."
        )
    frame = _parse(path, text, sep, decimal, names, header_row=not in_comment)
    where = _row_namer(text, 0 if in_comment else 1, len(frame))
    del text
    columns, unusable = _numeric_columns(path, frame, where, names)
    if len(frame) == 0:
        raise DataError(f"{path}: the file has a header but no rows.")
    origin = None
    if time_column is not None and time_column in unusable:
        columns[time_column], origin = _times_from_text(path, frame[time_column], time_column, unusable, where)
        del unusable[time_column]
    t, used = time_grid(columns, time_column, dt, str(path), where)
    return Table(t=t, columns=columns, source=str(path), dt=None if used else dt, time_column=used,
                 unusable=unusable, where=where, time_origin=origin)  # fmt: skip


def _text(path: Path) -> str:
    fix = "Split the recording into several files (data.path takes a glob) or decimate it"
    try:
        text = (
            _gunzipped(path, fix)
            if path.suffix.lower() == ".gz"
            else read_text(path, DATA_BYTES, f"data file {path}", fix)
        )
    except UnicodeDecodeError as err:
        raise DataError(
            f"{path}: not UTF-8 text (byte {err.start}: {err.reason}). Save the file as UTF-8 (plain ASCII is fine)."
        ) from None
    except FileNotFoundError:
        raise DataError(f"data file {path} does not exist (data.path={path}).") from None
    except OSError as err:
        raise DataError(f"data file {path} cannot be read ({err.strerror or err}).") from None
    return text.removeprefix("\ufeff")


def _gunzipped(path: Path, fix: str) -> str:
    """The text of a gzip-compressed file, at most `DATA_BYTES` once decompressed."""
    why = not_a_regular_file(path)
    if why is not None:
        raise DataError(f"data file {path} {why}.")
    try:
        with gzip.open(path, "rb") as handle:
            data = handle.read(DATA_BYTES + 1)
    except (OSError, EOFError) as err:
        raise DataError(
            f"{path}: cannot decompress as gzip ({err}). Give the file uncompressed, or gzip it again."
        ) from None
    if len(data) > DATA_BYTES:
        raise DataError(
            f"data file {path} holds over {size_text(DATA_BYTES)} once decompressed, over mpsim's limit. {fix}."
        )
    return data.decode("utf-8")


def _content_lines(text: str) -> tuple[list[tuple[int, str]], str]:
    """(line number, line) of the first `SNIFF_LINES` + 1 lines that are not blank and not a '#' comment, the header
    first (enough to tell the delimiter; the line of any other row is found when a message names it, `_row_namer`);
    and the last comment line before the first of them, without its '#' (a header written as a comment)."""
    out: list[tuple[int, str]] = []
    comment = ""
    start = 0
    number = 0
    while start <= len(text) and len(out) <= SNIFF_LINES:
        end = text.find("\n", start)
        end = len(text) if end < 0 else end
        line = text[start:end].rstrip("\r")
        number += 1
        stripped = line.strip()
        if stripped and not stripped.startswith("#"):
            out.append((number, line))
        elif stripped and not out:
            comment = stripped.lstrip("#")
        start = end + 1
    return out, comment


def _all_numbers(fields: list[str], decimal: str) -> bool:
    """Whether every field reads as a number (a data row, not a header)."""
    try:
        [float(f.strip().replace(decimal, ".")) for f in fields if f.strip()]
    except ValueError:
        return False
    return True


def _fields(line: str, sep: str) -> list[str]:
    if sep == " ":
        return line.split()
    return next(csv.reader([line], delimiter=sep, skipinitialspace=True), [])


def _sniff(path: Path, sample: list[tuple[int, str]], text: str) -> tuple[str, str]:
    """(delimiter, decimal mark) that split the header into more than one name and every sampled row into as many
    fields (one more, if the last is empty: a trailing delimiter). A file of one column is read with ','. A ';' file
    has decimal commas when a comma stands between two digits anywhere after its header (not only in the rows
    sampled: its first rows may hold whole numbers)."""
    fields = {sep: [_fields(line, sep) for _, line in sample] for sep in (*_DELIMITERS, " ")}
    names = {sep: _count(per_line[0]) for sep, per_line in fields.items()}
    for sep, per_line in fields.items():
        if names[sep] > 1 and all(_fits(f, names[sep]) for f in per_line[1:]):
            after_header = text.find("\n", text.find(sample[0][1])) if sample else 0
            decimal = "," if sep == ";" and _DECIMAL_COMMA.search(text, max(after_header, 0)) else "."
            return sep, decimal
    if all(len(f) == 1 for per_line in fields.values() for f in per_line):
        return ",", "."
    sep = next((s for s in fields if names[s] > 1), ",")
    k = next(i for i, f in enumerate(fields[sep]) if i and not _fits(f, names[sep]))
    shown = {",": "','", ";": "';'", "\t": "tabs", " ": "spaces"}[sep]
    raise DataError(
        f"{path}: line {sample[k][0]} holds {_count(fields[sep][k])} fields separated by {shown} but the header line "
        f"{sample[0][0]} holds {names[sep]}. Give every row one value per header name, separated like the header "
        "(',', ';', a tab or spaces)."
    )


def _count(fields: list[str]) -> int:
    """How many fields, a trailing empty one not counted."""
    return len(fields) - (len(fields) > 1 and fields[-1].strip() == "")


def _fits(fields: list[str], n: int) -> bool:
    """Whether a row's `fields` give one value per name of a header of `n` names (plus an empty trailing one)."""
    return len(fields) == n or (len(fields) == n + 1 and fields[-1].strip() == "")


def _header(path: Path, line: str, sep: str) -> list[str]:
    """The header's names, stripped; an empty last name (a trailing delimiter) is dropped."""
    names = [name.strip() for name in _fields(line, sep)]
    if len(names) > 1 and names[-1] == "":
        names = names[:-1]
    names = [name or f"column{j + 1}" for j, name in enumerate(names)]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise DataError(f"{path}: the header names {repeated} more than once; give every column its own name.")
    return names


def _parse(path: Path, text: str, sep: str, decimal: str, names: list[str], header_row: bool) -> pd.DataFrame:
    """The rows as a frame with the header's `names` (a trailing empty column dropped); vectorised.

    `header_row`: the first line that is not a comment is the header (else every such line is a row)."""
    options: dict[str, Any] = {"sep": r"\s+"} if sep == " " else {"sep": sep, "skipinitialspace": True}
    options["header"] = 0 if header_row else None
    if "#" in text and _COMMENT_LINE.search(text):  # whole comment lines go; a '#' in a cell stays (comment= cuts it)
        text = _COMMENT_LINE.sub("", text)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", pd.errors.ParserWarning)
            frame = pd.read_csv(io.StringIO(text), decimal=decimal, index_col=False, **options)
    except pd.errors.ParserWarning:
        raise DataError(
            f"{path}: some rows hold more fields than the header's {len(names)} names {names}. Give every row one "
            "value per header name (or name the extra columns in the header)."
        ) from None
    except (ValueError, pd.errors.ParserError) as err:
        raise DataError(f"{path}: cannot parse as CSV ({type(err).__name__}: {err}).") from None
    extra = frame.columns[len(names) :]
    if len(extra) and frame[extra].isna().all().all():
        frame = frame.drop(columns=extra)  # a trailing delimiter on every row
    if len(frame.columns) != len(names):
        raise DataError(
            f"{path}: the rows hold {len(frame.columns)} fields but the header names {len(names)} columns {names}."
        )
    frame.columns = pd.Index(names)
    return frame


def _row_namer(text: str, skip: int, n_rows: int) -> Callable[[int], str]:
    """row index -> "row i (line L)" when the file's line of each row is known, else "row i". The lines are
    counted the first time a row is named (`skip`: content lines before the first row, the header)."""
    numbers: list[int] = []

    def where(i: int) -> str:
        if not numbers:
            lines = enumerate(text.splitlines(), start=1)
            numbers.extend(n for n, line in lines if line.strip() and not line.lstrip().startswith("#"))
            del numbers[:skip]
        known = len(numbers) == n_rows  # quoted fields spanning lines would shift them
        return f"row {i + 1} (line {numbers[i]})" if known and 0 <= i < n_rows else f"row {i + 1}"

    return where


def _numeric_columns(
    path: Path, frame: pd.DataFrame, where: Callable[[int], str], names: list[str]
) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """{name: float64 values} of the numeric columns (empty cells are NaN), and {name: why} of those with text.
    A row with text in every column that has a value (a repeated header, a footer) is refused, named."""
    columns: dict[str, np.ndarray] = {}
    unusable: dict[str, str] = {}
    text_rows = np.ones(len(frame), dtype=bool)
    filled = np.zeros(len(frame), dtype=bool)
    numeric = False  # some column holds numbers (in rows other than text ones)
    for name in frame.columns:  # a loop over the few columns, each converted whole
        raw = frame[name]
        present = np.asarray(raw.notna().to_numpy())
        filled |= present
        if pd.api.types.is_numeric_dtype(raw.dtype) and not pd.api.types.is_bool_dtype(raw.dtype):
            columns[name] = raw.to_numpy(dtype=np.float64, na_value=np.nan)
            text_rows &= ~present
            numeric |= bool(present.any())
            continue
        values = pd.to_numeric(raw.astype("string").str.strip(), errors="coerce").to_numpy(
            dtype=np.float64, na_value=np.nan
        )
        text = present & np.isnan(values)
        text &= ~raw.astype("string").str.strip().str.lower().isin(["nan", "inf", "-inf", "+inf"]).to_numpy(bool)
        text_rows &= text | ~present
        numeric |= bool((present & ~text).any())
        if text.any():
            i = int(np.nonzero(text)[0][0])
            unusable[name] = f"{where(i)} holds {str(raw.iloc[i])!r}, not a number ({int(text.sum())} such cells)"
        else:
            columns[name] = values
    _refuse_text_rows(path, frame, np.nonzero(text_rows & filled)[0], where, names, numeric)
    return columns, unusable


def _refuse_text_rows(
    path: Path, frame: pd.DataFrame, rows: np.ndarray, where: Callable[[int], str], names: list[str], numeric: bool
) -> None:
    """A row of text in every column of a file that otherwise holds numbers: the header again (two files joined),
    a footer (the last rows), or a line of text: one message naming the row and the fix."""
    if not len(rows) or not numeric:
        return
    i = int(rows[0])
    cells = [str(v).strip() for v in frame.iloc[i].tolist() if not pd.isna(v)]
    shown = ", ".join(repr(c) for c in cells[:4]) + (", ..." if len(cells) > 4 else "")
    count = f" ({len(rows)} such rows)" if len(rows) > 1 else ""
    if cells == [n for n, v in zip(names, frame.iloc[i].tolist(), strict=False) if not pd.isna(v)]:
        raise DataError(
            f"{path}: {where(i)} repeats the header ({shown}){count}: the file looks like several recordings "
            "joined. Split it into one file per recording (data.path takes a pattern), or delete the repeated "
            "header lines."
        )
    if rows[-1] == len(frame) - 1 and len(rows) == len(frame) - i:
        raise DataError(
            f"{path}: {where(i)} holds text in every column ({shown}){count}, after the last row of numbers: a "
            "footer. Delete it, or start its lines with '#' (a comment)."
        )
    raise DataError(
        f"{path}: {where(i)} holds text in every column ({shown}){count}, between rows of numbers. Delete that line, "
        "or start it with '#' (a comment)."
    )


def _times_from_text(
    path: Path, raw: pd.Series, name: str, unusable: dict[str, str], where: Callable[[int], str]
) -> tuple[np.ndarray, str]:
    """A time column that holds text: ISO 8601 dates in every row become seconds since the first (returned with
    that first date); anything else is refused with the first cell that is not a number and what to write."""
    cells = raw.astype("string").str.strip()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            stamps = pd.to_datetime(cells, format="ISO8601")
    except (ValueError, TypeError, OverflowError):
        stamps = None
    if stamps is not None and not stamps.isna().any():
        delta = (stamps - stamps.iloc[0]).dt.total_seconds().to_numpy(dtype=np.float64)
        return delta, str(stamps.iloc[0])
    numbers = pd.to_numeric(cells, errors="coerce").to_numpy(dtype=np.float64, na_value=np.nan)
    bad = np.nonzero(np.isnan(numbers) & raw.notna().to_numpy(bool))[0]
    i = int(bad[0]) if len(bad) else 0
    cell = str(raw.iloc[i])
    hint = (
        " It is a number with a unit: write the number of seconds alone (0.35, not 0.35s)."
        if _WITH_UNIT.match(cell)
        else " Times must be numbers (seconds) or ISO 8601 dates in every row (2026-01-02 10:00:00.05)."
    )
    raise DataError(
        f"{path}: {where(i)}, time column '{name}' holds {cell!r}, not a time ({len(bad)} such cell"
        f"{'s' if len(bad) != 1 else ''}).{hint}"
    )
