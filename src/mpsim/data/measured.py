"""Measured recordings as they come: one wide CSV or `.mat` file per recording (or several by a glob), read into
the batch a model trains on, in small steps that each do one thing:

read (`mpsim.data.wide.read_wide_csv`, `mpsim.data.matfile.read_mat`) → map columns to the model's states and
inputs (`mpsim.data.recording.to_recording`, `data.columns`) → one uniform grid per recording (`data.resample`, or
the file's own clock if it runs steadily) → every k-th sample (`data.stride`) → latent states estimated
(`data.observed`, `mpsim.data.latent.estimate_latent`) → segments (`data.segment`) or whole recordings → the batch.
Splitting (contiguous blocks in time order) is the caller's (`mpsim.data.pipeline.load_splits`).
"""

from __future__ import annotations

import glob
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

from mpsim.data.grid import HOLDS, resample, stride, uniform_or_refuse
from mpsim.data.latent import estimate_latent
from mpsim.data.matfile import read_mat
from mpsim.data.recording import to_recording
from mpsim.data.segments import segment, stack_recordings
from mpsim.data.table import Table
from mpsim.data.trajectories import Trajectories
from mpsim.data.wide import read_wide_csv
from mpsim.errors import ConfigError, DataError
from mpsim.safeload import not_a_regular_file

log = logging.getLogger(__name__)

#: the columns that make a CSV the long format (one row per trajectory, time and node)
LONG_COLUMNS = ("traj", "t", "node")
#: bytes of a CSV's head looked at to tell the long format from a wide one
HEAD_BYTES = 65536
GLOB_CHARS = "*?["


@dataclass(frozen=True)
class Recordings:
    """How measured recordings become a batch (the `data.*` keys that concern them, as plain values).

    Attributes:
        time_column: the time column (None: none; samples `dt` apart).
        dt: the step of a file without a time column.
        columns: {model name: file column} (names not in it are looked up as themselves).
        controls: the model's inputs (`data.control_columns`), in its order.
        observed: the states the files hold (empty: all of `states`, or every non-time non-control column).
        states: the model's states in its order, when the model states them (a spec); None: the file's.
        rates: {latent state s: measured o} for each equation ``o' = s`` (how a latent state is estimated).
        resample, stride, segment, input_hold: `data.resample`, `data.stride`, `data.segment`, `data.input_hold`.
    """

    time_column: str | None = "t"
    dt: float | None = None
    columns: Mapping[str, str] = field(default_factory=dict)
    controls: Sequence[str] = ()
    observed: Sequence[str] = ()
    states: Sequence[str] | None = None
    rates: Mapping[str, str] = field(default_factory=dict)
    resample: float | None = None
    stride: int = 1
    segment: float | None = None
    input_hold: str = "linear"


def paths_of(path: Path) -> list[Path]:
    """The files `path` names: itself, or the files a glob matches, sorted by name (one recording each)."""
    if not any(c in str(path) for c in GLOB_CHARS):
        return [path]
    found = sorted(Path(p) for p in glob.glob(str(path)))
    files = [p for p in found if p.is_file()]
    if not files:
        raise DataError(f"data.path={path}: the pattern matches no file{'' if not found else ' (only folders)'}.")
    return files


def is_recording(path: Path) -> bool:
    """Whether `path` is read as a recording (wide CSV or `.mat`), not as a batch of trajectories (npz, long CSV)."""
    suffix = path.suffix.lower()
    if suffix == ".mat":
        return True
    if suffix != ".csv" or not path.is_file():
        return False
    return not _long_header(path)


def _long_header(path: Path) -> bool:
    """Whether the CSV's first line that is not a comment names the long format's columns traj, t and node."""
    with open(path, "rb") as f:
        head = f.read(HEAD_BYTES).decode("utf-8", errors="replace").lstrip("\ufeff")
    for line in head.splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            names = {c.strip().strip("\"'").strip() for c in line.replace(";", ",").replace("\t", ",").split(",")}
            return set(LONG_COLUMNS) <= names
    return False


def read_table(path: Path, how: Recordings) -> Table:
    """One file's columns: a wide CSV or a `.mat` file (one message for a missing or special file)."""
    why = not_a_regular_file(path)
    if why:
        raise DataError(f"data file {path} {why}.")
    if path.suffix.lower() == ".mat":
        return read_mat(path, how.time_column, how.dt)
    return read_wide_csv(path, how.time_column, how.dt)


def _states_in_file(table: Table, how: Recordings) -> list[str]:
    """The model states a file holds, in the model's order: `data.observed`; else the model's states; else the
    names `data.columns` maps (its controls apart); else every numeric column but the time and the controls."""
    if how.observed:
        return list(how.observed)
    if how.states is not None:
        return list(how.states)
    mapped = [name for name in how.columns if name not in how.controls]
    if mapped:
        return mapped
    used = {how.columns.get(c, c) for c in how.controls} | {table.time_column}
    return [name for name in table.columns if name not in used]


def one_recording(path: Path, how: Recordings) -> Trajectories:
    """One file as a recording on a uniform grid: read, columns mapped, resampled or its clock checked, strided,
    its latent states estimated."""
    table = read_table(path, how)
    rec = to_recording(table, how.columns, _states_in_file(table, how), list(how.controls))
    rec = replace(rec, meta={**rec.meta, "input_hold": how.input_hold})
    rec = resample(rec, how.resample, how.input_hold) if how.resample else uniform_or_refuse(rec)
    if how.stride != 1:
        rec = stride(rec, how.stride)
    return _with_latent(rec, how)


def _with_latent(rec: Trajectories, how: Recordings) -> Trajectories:
    """`rec` with the model's states that the file lacks estimated (each from the measured state it is the rate of)."""
    if how.states is None or list(how.states) == rec.state_names:
        return rec
    missing = [s for s in how.states if s not in rec.state_names]
    cannot = [s for s in missing if how.rates.get(s) not in rec.state_names]
    if cannot:
        raise ConfigError(
            f"data.observed={list(how.observed)}: the model's state(s) {cannot} are not measured and no measured "
            "state's equation is that state (o' = s), so they cannot be estimated. Add their columns to the data "
            "(data.columns) or to data.observed."
        )
    return estimate_latent(rec, {s: how.rates[s] for s in missing}, states=list(how.states))


def read_recordings(path: Path, how: Recordings) -> Trajectories:
    """The batch of every recording `path` names (a file or a glob): their segments of `data.segment` seconds,
    or the whole recordings when they share one length."""
    if how.input_hold not in HOLDS:
        raise ConfigError(f"data.input_hold must be one of {list(HOLDS)}; got {how.input_hold!r}.")
    if how.stride < 1:
        raise ConfigError(f"data.stride must be a whole number >= 1; got {how.stride}.")
    files = paths_of(path)
    longs = [p for p in files if not is_recording(p)]
    if longs and len(files) > 1:
        raise DataError(
            f"data.path={path} matches {len(files)} files, {longs[0].name} among them an .npz or long CSV; a pattern "
            "reads recordings (wide CSV or .mat files), one per file. Give a batch file by its name."
        )
    recs = [one_recording(p, how) for p in files]
    batch = stack_recordings(recs) if how.segment is None else segment(recs, how.segment)
    batch.meta["input_hold"] = how.input_hold
    log.info(
        f"read {len(recs)} recording(s) from {path}: {len(batch)} {'segments' if how.segment else 'trajectories'} "
        f"of {batch.n_times} samples, states {batch.state_names}, inputs {batch.control_names}"
    )
    return batch
