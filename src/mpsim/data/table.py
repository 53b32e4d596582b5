"""`Table`: the named columns of one measured recording as read from a file, before they are mapped to a model.

The readers (`mpsim.data.wide.read_wide_csv`, `mpsim.data.matfile.read_mat`) make one; `mpsim.data.recording.
to_recording` picks and renames its columns into a `Trajectories`. The time column is checked here, once for every
format: finite and strictly increasing (`check_times`), or made from `data.dt` when the file has none (`time_grid`).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mpsim.errors import DataError, did_you_mean

#: suffixes read as text tables (wide or long CSV); ".gz" of any of them is read decompressed
TEXT_SUFFIXES = (".csv", ".txt", ".dat", ".tsv")
#: the largest data file (wide CSV or .mat) mpsim reads; far above a 131 072-row recording (about 15 MB as CSV)
DATA_BYTES = 1 << 30


@dataclass(frozen=True)
class Table:
    """Columns of one recording.

    Attributes:
        t: [T] float64 absolute times (the file's time column, or k·`data.dt`), or None when the file has no time
            column and its columns differ in length (a `.mat` file: the length comes from the columns picked).
        columns: {name: [T_name] float64} every numeric column (a `.mat` file's variables may differ in length;
            a CSV's all have T). Non-finite values are kept: only the columns a model uses must be finite.
        source: the file, as messages name it.
        dt: the `data.dt` the times were made from (None: from the file's time column).
        time_column: the column the times came from (None: made from `data.dt`).
        unusable: {name: why} variables that could not become columns (text, cell arrays, 3-D arrays, ...).
        where: row index -> how a message names that row ("row 5 (line 7)"); default "row <i + 1>".
        time_origin: the date of the first row when the time column held ISO 8601 dates (times are then seconds
            since it), else None.
    """

    t: np.ndarray | None  # [T] float64 absolute times
    columns: dict[str, np.ndarray]  # {name: [T] float64}
    source: str
    dt: float | None = None
    time_column: str | None = None
    unusable: dict[str, str] = field(default_factory=dict)
    where: Callable[[int], str] | None = None
    time_origin: str | None = None

    def row(self, i: int) -> str:
        """How a message names row `i` (0-based) of the file."""
        return self.where(i) if self.where is not None else f"row {i + 1}"


def table_suffix(path: str | Path) -> str:
    """The suffix that tells a file's format, past a ``.gz``: ``rec.csv.gz`` -> ``.csv``."""
    suffixes = [s.lower() for s in Path(path).suffixes]
    if suffixes and suffixes[-1] == ".gz":
        suffixes = suffixes[:-1]
    return suffixes[-1] if suffixes else ""


def check_times(t: np.ndarray, source: str, column: str, where: Callable[[int], str]) -> None:  # t: [T] float64
    """Refuse times that are not finite or not strictly increasing, naming the file, the row and the fix."""
    if len(t) < 2:
        raise DataError(f"{source}: the recording has {len(t)} sample(s); need at least 2 time points.")
    bad = ~np.isfinite(t)
    if bad.any():
        i = int(np.nonzero(bad)[0][0])
        raise DataError(
            f"{source}: {where(i)}, time column '{column}' holds {t[i]} (not a finite number; {int(bad.sum())} "
            "such values). Fill in the time of that sample or remove the row."
        )
    steps = np.diff(t)
    if (steps <= 0).any():
        i = int(np.nonzero(steps <= 0)[0][0]) + 1
        what = "repeats" if steps[i - 1] == 0 else "goes back to"
        raise DataError(
            f"{source}: {where(i)}, time column '{column}' {what} {float(t[i])!r} after {float(t[i - 1])!r} in the row before; "
            "times must be strictly increasing. Sort the rows by time and drop repeated samples, or, if the clock "
            "restarted, split the file in two (data.path can take several files)."
        )


def time_grid(
    columns: dict[str, np.ndarray],
    time_column: str | None,
    dt: float | None,
    source: str,
    where: Callable[[int], str],
) -> tuple[np.ndarray | None, str | None]:
    """The times of a recording and the column they came from (None: made from `dt`), from its `columns`.

    The time column is used when the file has it (and `dt`, if given, must agree with its median step within 1 %);
    without it, `dt` gives t = k·dt — for the default name ``t`` only: a time column named explicitly must exist.
    When the columns differ in length (a `.mat` file) and there is no time column, the times are None and
    `mpsim.data.recording.to_recording` makes them from the length of the columns it picks.
    """
    if dt is not None and not (np.isfinite(dt) and dt > 0):
        raise DataError(f"{source}: data.dt must be a finite number > 0 (the sampling step in seconds); got {dt}.")
    if time_column is not None and time_column in columns:
        t = np.asarray(columns[time_column], dtype=np.float64)
        check_times(t, source, time_column, where)
        step = float(np.median(np.diff(t)))
        if dt is not None and abs(step - dt) > 0.01 * dt:
            raise DataError(
                f"{source}: the time column '{time_column}' steps by {step:.6g} s (median) but data.dt={dt:g}. "
                "Drop data.dt to use the file's times, or set data.time_column=null to use data.dt instead."
            )
        return t, time_column
    looks = _time_like(columns, time_column)
    if dt is not None and time_column == "t" and looks is not None:
        raise DataError(
            f"{source}: column '{looks}' looks like the file's times (increasing), but data.time_column is 't', "
            f"which the file lacks, so data.dt={dt:g} would put the samples {dt:g} s apart and ignore '{looks}' "
            f"(and any gap in it). Use the file's times with data.time_column={looks} (and drop data.dt), or, if "
            f"'{looks}' is not the time, say the file has none with data.time_column=null."
        )
    if dt is None or (time_column is not None and time_column != "t"):
        names = sorted(columns)
        hint = did_you_mean(time_column, names) if time_column else ""
        if looks is not None and looks != time_column and not hint:
            hint = f" Column '{looks}' looks like the times: data.time_column={looks}."
        raise DataError(
            f"{source}: no time column '{time_column}' (data.time_column) among the file's columns {names}.{hint} "
            "Name the time column with data.time_column=<name>, or, for a file without one, give the sampling step "
            "with data.dt=<seconds> (and data.time_column=null)."
        )
    lengths = {len(v) for v in columns.values()}
    if len(lengths) != 1:
        return None, None
    return np.arange(lengths.pop(), dtype=np.float64) * dt, None


#: column names that say "time" (t, time, Time [s], timestamp, t_s, seconds, zeit, ...)
_TIME_NAME = re.compile(r"^\s*(t|time|times|timestamps?|zeit|sec|secs|seconds|t_?s)\b|time", re.I)


def _time_like(columns: dict[str, np.ndarray], not_this: str | None) -> str | None:
    """The first column whose name says "time" and whose values strictly increase (None if there is none)."""
    for name, values in columns.items():
        if name == not_this or not _TIME_NAME.search(name) or len(values) < 2:
            continue
        steps = np.diff(np.asarray(values, dtype=np.float64))
        if np.isfinite(steps).all() and (steps > 0).all():
            return name
    return None
