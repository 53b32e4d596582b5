"""Map a file's columns to a model's states and inputs: a `Table` becomes one recording, a `Trajectories`.

A recording is B = 1 trajectory of N = 1 node on the file's own time grid, counted from its first sample (jitter
allowed while strictly increasing; the file's first time is kept in ``meta['t0']``, so times of 1.7e9 s since 1970
lose no digits): ``x`` [1, T, 1, D] states, ``u`` [1, T, 1, C] inputs (or None), and ``meta`` with ``system`` (the
file's stem), ``source`` (its path), ``state_names``, ``control_names``, ``columns`` (model name -> file column),
``dt`` (the median step), ``t0`` ([the file's first time]) and ``rows`` (samples read). Several files make a list of
recordings.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch

from mpsim.data.table import Table
from mpsim.data.trajectories import Trajectories
from mpsim.errors import DataError, did_you_mean

#: a value this many times a column's typical magnitude (its 99th percentile of |x|) is no reading: an overflow or
#: a missing-value code, refused with its row
OUTLIER_FACTOR = 1e6
#: the largest magnitude each precision holds (float64: normalisation squares values, so 1e150)
LIMITS = {"float32": float(np.finfo(np.float32).max), "float64": 1e150}


def to_recording(
    table: Table,
    columns: Mapping[str, str] | None,
    states: Sequence[str],
    controls: Sequence[str] = (),
    dtype_name: str = "float64",
) -> Trajectories:
    """The recording of `table` with the columns `states` and `controls` picked, in that order, and renamed.

    Args:
        table: a file's columns (`mpsim.data.wide.read_wide_csv`, `mpsim.data.matfile.read_mat`).
        columns: `data.columns`, {model name: file column}; a name not in it is looked up as itself.
        states: the model's states that the file holds (`data.observed`; all of them when every state is
            measured), in the model's order. The others are filled later (`mpsim.data.latent.estimate_latent`).
        controls: the model's inputs (`data.control_columns`), in the model's order.
        dtype_name: the model's precision: a value it cannot hold is refused here, with its row.

    Returns:
        `Trajectories` with B = 1, N = 1 (module docstring).

    Raises:
        DataError: a name whose column the file lacks (the file's columns listed, with a did-you-mean), a column
            that holds text, whose length is not the time column's, or that holds an empty cell, NaN or inf, a
            value the model's precision cannot hold, or one `OUTLIER_FACTOR` times the column's typical magnitude.
    """
    columns = dict(columns or {})
    if not states:
        raise DataError(f"{table.source}: no state to read (data.observed is empty); list the measured states.")
    picked = {name: _column(table, name, columns.get(name, name)) for name in (*states, *controls)}
    t = table.t if table.t is not None else _made_times(table, picked)
    for name, values in picked.items():
        _check_values(table, name, columns.get(name, name), values, len(t))
        _check_range(table, name, columns.get(name, name), values, dtype_name)
    x = np.stack([picked[s] for s in states], axis=-1)[None, :, None, :]
    u = np.stack([picked[c] for c in controls], axis=-1)[None, :, None, :] if controls else None
    time = torch.from_numpy(np.asarray(t, dtype=np.float64) - float(t[0]))  # from the first sample: no digit lost
    meta = {
        "system": Path(table.source).stem,
        "source": table.source,
        "state_names": list(states),
        "control_names": list(controls),
        "columns": {name: columns.get(name, name) for name in (*states, *controls)},
        "dt": float(np.median(np.diff(t))),
        "t0": [float(t[0])],
        "time_column": table.time_column,
        "rows": len(t),
    }
    if table.time_origin is not None:
        meta["time_origin"] = table.time_origin
    return Trajectories(
        t=time,
        x=torch.from_numpy(np.ascontiguousarray(x)),
        edge_index=torch.zeros(2, 0, dtype=torch.long),
        u=None if u is None else torch.from_numpy(np.ascontiguousarray(u)),
        meta=meta,
    )


def _column(table: Table, name: str, column: str) -> np.ndarray:  # -> [T_column] float64
    """The file's `column` for the model's `name`, or one message naming what the file has."""
    if column in table.columns:
        return table.columns[column]
    mapped = f"'{name}' (mapped to column '{column}' by data.columns)" if column != name else f"'{name}'"
    if column in table.unusable:
        raise DataError(
            f"{table.source}: the column for {mapped} cannot be used: it is {table.unusable[column]}. Map "
            f"'{name}' to a numeric column with data.columns={{{name}: <column>}}, or fix the file."
        )
    found = sorted([*table.columns, *table.unusable])
    raise DataError(
        f"{table.source}: no column for {mapped}; the file's columns are {found}.{did_you_mean(column, found)} "
        f"Map it with data.columns={{{name}: <column>}}, or, if the file does not measure '{name}', leave it out "
        "of data.observed (an unmeasured state is estimated) or data.control_columns."
    )


def _made_times(table: Table, picked: dict[str, np.ndarray]) -> np.ndarray:  # -> [T] float64
    """k·`data.dt` for a file without a time column whose columns differ in length: the picked ones must agree."""
    lengths = {name: len(v) for name, v in picked.items()}
    if len(set(lengths.values())) > 1:
        raise DataError(
            f"{table.source}: the columns used have different lengths {lengths} and the file has no time column to "
            "tell which samples belong together. Use variables of one length, or add a time variable "
            "(data.time_column)."
        )
    assert table.dt is not None  # time_grid returns no times only when data.dt is given
    return np.arange(next(iter(lengths.values())), dtype=np.float64) * table.dt


def _check_values(table: Table, name: str, column: str, values: np.ndarray, n_times: int) -> None:
    if len(values) != n_times:
        what = f"the time column '{table.time_column}'" if table.time_column else "the other columns used"
        raise DataError(
            f"{table.source}: column '{column}' (for '{name}') has {len(values)} samples but {what} has "
            f"{n_times}. Only variables with the time column's length can be used: map '{name}' to one of those, "
            "or resample the variable in the file."
        )
    bad = ~np.isfinite(values)
    if bad.any():
        i = int(np.nonzero(bad)[0][0])
        what = "is empty or NaN" if np.isnan(values[i]) else f"holds {float(values[i])}"
        raise DataError(
            f"{table.source}: {table.row(i)}, column '{column}' (for '{name}') {what} (not a finite number; "
            f"{int(bad.sum())} such values in that column). Remove or interpolate those rows."
        )


def _check_range(table: Table, name: str, column: str, values: np.ndarray, dtype_name: str) -> None:
    """Refuse a value the model's precision cannot hold, or one so far above the column's typical magnitude that
    it is no reading (an overflow, a missing-value code), naming its row."""
    size = np.abs(values)
    i = int(np.argmax(size))
    peak = float(size[i])
    limit = LIMITS.get(dtype_name, LIMITS["float64"])
    if peak > limit:
        fix = "rescale it (other units) or use dtype=float64" if dtype_name == "float32" else "rescale it"
        raise DataError(
            f"{table.source}: {table.row(i)}, column '{column}' (for '{name}') holds {values[i]:.3g}, beyond what "
            f"dtype={dtype_name} holds (up to {limit:.3g}). Fix the row, or {fix}."
        )
    typical = float(np.percentile(size, 99)) if len(size) >= 10 else 0.0
    if typical > 0 and peak > OUTLIER_FACTOR * typical:
        many = int((size > OUTLIER_FACTOR * typical).sum())
        raise DataError(
            f"{table.source}: {table.row(i)}, column '{column}' (for '{name}') holds {values[i]:.3g}, "
            f"{peak / typical:.2g} times the column's typical magnitude ({typical:.3g}, the 99th percentile of "
            f"|{column}|; {many} such value{'s' if many != 1 else ''}): a sensor overflow or a missing-value code, "
            "not a reading. Delete or correct that row."
        )
