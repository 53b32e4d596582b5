"""Wide CSV: one measured recording per file, one row per sample, one column per signal.

```
time,position,velocity,torque
0.000,-0.0015,0.121,-0.004
0.002,-0.0015,-0.077,-0.532
```

Read as it comes from a lab: the delimiter is sniffed (``,`` ``;`` tab, or runs of spaces; ``;`` with decimal
commas), headers may be quoted or padded with spaces, a trailing delimiter (an empty last column), a UTF-8 byte-order
mark, blank lines and ``#`` comment lines are ignored. The time column is `data.time_column` (default ``t``); a file
without one needs `data.dt`. Columns holding text are set aside (named if a model asks for them); empty cells and
NaN/inf are refused when a model uses that column (`mpsim.data.recording.to_recording`). Reading is vectorised
(pandas' C parser): 131 072 rows of four columns take about 0.2 s.
"""

from __future__ import annotations

import csv
import io
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from mpsim.data.table import DATA_BYTES, Table, time_grid
from mpsim.errors import DataError
from mpsim.safeload import read_text

#: lines read to tell the delimiter
SNIFF_LINES = 50
_DELIMITERS = (",", ";", "\t")


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
    sep, decimal = _sniff(path, lines[: SNIFF_LINES + 1])
    in_comment = _all_numbers(_fields(lines[0][1], sep), decimal)  # np.savetxt writes its header as "# t,q,u"
    names = _header(path, comment if in_comment else lines[0][1], sep)
    if in_comment and (not comment.strip() or len(names) != len(_header(path, lines[0][1], sep))):
        raise DataError(
            f"{path}: line {lines[0][0]} holds numbers, not column names: the file has no header. Add a first line "
            "naming the columns (e.g. t,q,u), separated like the rows."
        )
    frame = _parse(path, text, sep, decimal, names, header_row=not in_comment)
    where = _row_namer([number for number, _ in (lines if in_comment else lines[1:])], len(frame))
    columns, unusable = _numeric_columns(frame, where)
    if len(frame) == 0:
        raise DataError(f"{path}: the file has a header but no rows.")
    t, used = time_grid(columns, time_column, dt, str(path), where)
    return Table(t=t, columns=columns, source=str(path), dt=None if used else dt, time_column=used,
                 unusable=unusable, where=where)  # fmt: skip


def _text(path: Path) -> str:
    fix = "Split the recording into several files (data.path takes a glob) or decimate it"
    try:
        text = read_text(path, DATA_BYTES, f"data file {path}", fix)
    except UnicodeDecodeError as err:
        raise DataError(
            f"{path}: not UTF-8 text (byte {err.start}: {err.reason}). Save the file as UTF-8 (plain ASCII is fine)."
        ) from None
    except FileNotFoundError:
        raise DataError(f"data file {path} does not exist (data.path={path}).") from None
    except OSError as err:
        raise DataError(f"data file {path} cannot be read ({err.strerror or err}).") from None
    return text.removeprefix("\ufeff")


def _content_lines(text: str) -> tuple[list[tuple[int, str]], str]:
    """(line number, line) of every line that is not blank and not a '#' comment, the header first; and the last
    comment line before the first of them, without its '#' (a header written as a comment).

    Only the texts of the first `SNIFF_LINES` are kept (enough to tell the delimiter); the line numbers of all rows
    are kept to name them in messages (about 30 ms for 131 072 rows)."""
    out: list[tuple[int, str]] = []
    comment = ""
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if stripped and not stripped.startswith("#"):
            out.append((number, line if len(out) <= SNIFF_LINES else ""))
        elif stripped and not out:
            comment = stripped.lstrip("#")
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


def _sniff(path: Path, sample: list[tuple[int, str]]) -> tuple[str, str]:
    """(delimiter, decimal mark) that split the header into more than one name and every sampled row into as many
    fields (one more, if the last is empty: a trailing delimiter). A file of one column is read with ','."""
    fields = {sep: [_fields(line, sep) for _, line in sample] for sep in (*_DELIMITERS, " ")}
    names = {sep: _count(per_line[0]) for sep, per_line in fields.items()}
    for sep, per_line in fields.items():
        if names[sep] > 1 and all(_fits(f, names[sep]) for f in per_line[1:]):
            decimal = "," if sep == ";" and any("," in line for _, line in sample[1:]) else "."
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
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", pd.errors.ParserWarning)
            frame = pd.read_csv(io.StringIO(text), decimal=decimal, comment="#", index_col=False, **options)
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


def _row_namer(numbers: list[int], n_rows: int) -> Callable[[int], str]:
    """row index -> "row i (line L)" when the file's line of each row is known, else "row i"."""
    known = len(numbers) == n_rows  # quoted fields spanning lines would shift them

    def where(i: int) -> str:
        return f"row {i + 1} (line {numbers[i]})" if known and 0 <= i < n_rows else f"row {i + 1}"

    return where


def _numeric_columns(frame: pd.DataFrame, where: Callable[[int], str]) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """{name: float64 values} of the numeric columns (empty cells are NaN), and {name: why} of those with text."""
    columns: dict[str, np.ndarray] = {}
    unusable: dict[str, str] = {}
    for name in frame.columns:  # a loop over the few columns, each converted whole
        raw = frame[name]
        if pd.api.types.is_numeric_dtype(raw.dtype) and not pd.api.types.is_bool_dtype(raw.dtype):
            columns[name] = raw.to_numpy(dtype=np.float64, na_value=np.nan)
            continue
        values = pd.to_numeric(raw.astype("string").str.strip(), errors="coerce").to_numpy(
            dtype=np.float64, na_value=np.nan
        )
        text = np.asarray(raw.notna().to_numpy()) & np.isnan(values)
        text &= ~raw.astype("string").str.strip().str.lower().isin(["nan", "inf", "-inf", "+inf"]).to_numpy(bool)
        if text.any():
            i = int(np.nonzero(text)[0][0])
            unusable[name] = f"{where(i)} holds {str(raw.iloc[i])!r}, not a number ({int(text.sum())} such cells)"
        else:
            columns[name] = values
    return columns, unusable
