"""Measured recordings as they come: one wide CSV or `.mat` file per recording (or several by a pattern), read into
the batch a model trains on, in small steps that each do one thing:

read (`mpsim.data.wide.read_wide_csv`, `mpsim.data.matfile.read_mat`) → map columns to the model's states and
inputs (`mpsim.data.recording.to_recording`, `data.columns`) → noise level and quantisation step of each signal
as recorded (``meta["noise"]``, `mpsim.data.noise.noise_summary`) → split at gaps in the clock
(`mpsim.data.gaps`) → one uniform grid per piece (`data.resample`, or the file's own clock if it runs steadily) →
every k-th sample (`data.stride`) → latent states estimated (`data.observed`, `mpsim.data.latent.estimate_latent`)
→ segments (`data.segment`) or whole recordings → the batch. Splitting (contiguous blocks in time order) is the
caller's (`mpsim.data.pipeline.load_splits`).

Every sample is accounted for (``meta["account"]``, `mpsim.data.account`): the files a pattern matched, the rows
of each, its gaps (split or filled), the pieces too short to use, and the samples after the last whole segment.
A file that exists is read as named, even when its name holds ``[`` or ``*``; a name is a pattern only when no
file has it. Two files holding the same samples are refused (a copy would sit in training and test at once).
"""

from __future__ import annotations

import glob
import hashlib
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from mpsim.data.account import account_lines
from mpsim.data.clipped import clipped_channels, clipped_text
from mpsim.data.gaps import split_at_gaps
from mpsim.data.grid import HOLDS, check_resample_step, resample, stride, uniform_or_refuse
from mpsim.data.latent import MIN_WINDOW, estimate_latent
from mpsim.data.matfile import read_mat
from mpsim.data.noise import noise_summary
from mpsim.data.recording import to_recording
from mpsim.data.segments import segment, stack_recordings
from mpsim.data.table import TEXT_SUFFIXES, Table, table_suffix
from mpsim.data.trajectories import Trajectories
from mpsim.data.wide import read_wide_csv
from mpsim.errors import ConfigError, DataError, did_you_mean
from mpsim.memory import check_fits
from mpsim.safeload import not_a_regular_file

log = logging.getLogger(__name__)

#: the columns that make a CSV the long format (one row per trajectory, time and node)
LONG_COLUMNS = ("traj", "t", "node")
#: bytes of a CSV's head looked at to tell the long format from a wide one
HEAD_BYTES = 65536
GLOB_CHARS = "*?["
#: memory that reading a text file takes, as a multiple of its size (text, parsed frame, float columns): a 160 MB
#: CSV of four columns peaked at 1.0 GB above the interpreter's own
READ_FACTOR = 8


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
        inputs: the model's inputs when it states them (a spec's `inputs:`): read when `controls` is empty.
        dtype_name: the model's precision (a value it cannot hold is refused with its file row).
        memory_check: refuse a file whose reading would not fit in memory (`memory_check`; `READ_FACTOR`).
        outputs: the spec's outputs (what its sensors read); `states` then lists the states and the outputs, and
            the file holds the outputs unless `data.observed` says otherwise.
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
    inputs: Sequence[str] | None = None
    dtype_name: str = "float64"
    memory_check: bool = True
    outputs: Sequence[str] = ()


def is_pattern(path: Path) -> bool:
    """Whether `path` is read as a pattern: it holds `*`, `?` or `[` and no file or folder has that very name."""
    return any(c in str(path) for c in GLOB_CHARS) and not path.exists()


def paths_of(path: Path) -> list[Path]:
    """The files `path` names: itself when it exists (``rec[1].csv`` is that file), else the files it matches as a
    pattern, sorted by name (one recording each). A missing file or a folder is refused, with what is there."""
    if not is_pattern(path):
        why = not_a_regular_file(path)
        if why == "does not exist":
            here = sorted(p.name for p in path.parent.iterdir()) if path.parent.is_dir() else []
            where = "" if path.parent.is_dir() else f" (nor does the folder {path.parent})"
            raise DataError(f"data file {path} does not exist{where} (data.path).{did_you_mean(path.name, here)}")
        if why is not None and path.is_dir():
            raise DataError(
                f"data.path={path} is a folder. Give one of its files, or all its recordings as a pattern: "
                f"data.path='{path / '*.csv'}'."
            )
        return [path]
    found = sorted(Path(p) for p in glob.glob(str(path)))
    files = [p for p in found if p.is_file()]
    if not files:
        raise DataError(f"data.path={path}: the pattern matches no file{'' if not found else ' (only folders)'}.")
    return files


def is_recording(path: Path) -> bool:
    """Whether `path` is read as a recording (wide CSV or `.mat`), not as a batch of trajectories (npz, long CSV)."""
    suffix = table_suffix(path)
    if suffix == ".mat":
        return True
    if suffix not in TEXT_SUFFIXES or not path.is_file():
        return False
    return not _long_header(path)


def _long_header(path: Path) -> bool:
    """Whether the CSV's first line that is not a comment names the long format's columns traj, t and node."""
    import gzip

    opener: Any = gzip.open if path.suffix.lower() == ".gz" else open
    try:
        with opener(path, "rb") as f:
            head = f.read(HEAD_BYTES).decode("utf-8", errors="replace").lstrip("\ufeff")
    except (OSError, EOFError):
        return False  # the reader names what is wrong with it
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
    _check_read_memory(path, how.memory_check)
    if table_suffix(path) == ".mat":
        return read_mat(path, how.time_column, how.dt)
    return read_wide_csv(path, how.time_column, how.dt)


def _check_read_memory(path: Path, enabled: bool) -> None:
    """Refuse, before reading, a file whose reading would not fit in memory (about `READ_FACTOR` times its size;
    a `.gz` file by the size it states for its content)."""
    size = path.stat().st_size
    if path.suffix.lower() == ".gz" and size >= 4:
        with open(path, "rb") as f:  # gzip's trailer: the content's size modulo 4 GiB
            f.seek(-4, 2)
            size = max(size, int.from_bytes(f.read(4), "little"))
    check_fits(
        READ_FACTOR * size,
        f"reading {path.name} ({size / 2**20:.0f} MB of text)",
        "cpu",
        enabled,
        "split the recording into several files, which data.path reads as a pattern, or decimate it before "
        "reading: data.stride thins the samples only once they are read",
    )


def _states_in_file(table: Table, how: Recordings) -> list[str]:
    """The model states a file holds, in the model's order: `data.observed`; else the model's states; else the
    names `data.columns` maps (its controls apart); else every numeric column but the time and the controls."""
    if how.observed:
        return list(how.observed)
    if how.outputs:
        return list(how.outputs)  # a spec with outputs: the sensors' readings are what the file holds
    if how.states is not None:
        return list(how.states)
    mapped = [name for name in how.columns if name not in how.controls]
    if mapped:
        return mapped
    used = {how.columns.get(c, c) for c in how.controls} | {table.time_column}
    return [name for name in table.columns if name not in used]


def _controls(how: Recordings) -> list[str]:
    """The model's inputs to read: `data.control_columns`, else a spec's `inputs:` (by name, through
    `data.columns`)."""
    return list(how.controls) if how.controls else list(how.inputs or [])


def one_recording(
    path: Path, how: Recordings, rows: Sequence[int] | None = None
) -> tuple[list[Trajectories], dict[str, Any]]:
    """One file as pieces of a recording on uniform grids (one piece unless its clock has gaps): read, columns
    mapped, its rows `rows` = [start, stop) kept (`data.train_range`, ...; None: all), split at gaps, resampled or
    its clock checked, strided, its latent states estimated; and the file's entry of the account (rows, gaps,
    pieces)."""
    table = read_table(path, how)
    rec = to_recording(table, how.columns, _states_in_file(table, how), _controls(how), how.dtype_name)
    rec = replace(rec, meta={**rec.meta, "input_hold": how.input_hold, "noise": noise_summary(rec)})
    for warning in hold_warnings(rec, how.input_hold):
        log.warning(warning)
    observed = set(_observed_names(how)) or set(rec.state_names)
    measured = [d for d, name in enumerate(rec.state_names) if name in observed]
    clipped = clipped_channels(rec.x[0, :, 0][:, measured].double(), [rec.state_names[d] for d in measured])
    for c in clipped:
        log.warning(f"{path.name}: {clipped_text(c)}.")
    digest = _digest(rec)
    if rows is not None:
        rec = take_rows(rec, rows)
    pieces, gaps = split_at_gaps(rec, fill=bool(how.resample))
    origin = float(rec.meta["t0"][0])
    entry: dict[str, Any] = {
        "file": str(path),
        "rows": rec.n_times,
        "span": [origin + float(rec.t[0]), origin + float(rec.t[-1])],
        "gaps": gaps,
        "pieces": [],
        "digest": digest,
    }
    if rows is not None:
        entry["range"] = [int(rows[0]), int(rows[1])]
    if table.time_origin is not None:
        entry["time_origin"] = table.time_origin
    if clipped:
        entry["clipped"] = clipped
    for alone in (a for g in gaps for a in g.get("alone", [])):  # a sample alone between gaps: named, not used
        entry["pieces"].append(
            {"piece": alone["piece"], "rows": 1, "span": [alone["t"], alone["t"]], "skipped": "a single sample"}
        )
    out = []
    for piece in pieces:  # a loop over the few pieces of one file
        origin = float(piece.meta["t0"][0])
        part: dict[str, Any] = {
            "piece": int(piece.meta.get("piece", 1)),
            "rows": piece.n_times,
            "span": [origin + float(piece.t[0]), origin + float(piece.t[-1])],
        }
        entry["pieces"].append(part)
        why = _too_short(piece, how)
        if why is not None:
            part["skipped"] = why
            continue
        piece = resample(piece, how.resample, how.input_hold) if how.resample else uniform_or_refuse(piece)
        if how.stride != 1:
            piece = stride(piece, how.stride, how.input_hold)
        part["samples"] = piece.n_times
        out.append(_with_latent(piece, how))
    entry["pieces"].sort(key=lambda part: part["piece"])
    return out, entry


def _too_short(piece: Trajectories, how: Recordings) -> str | None:
    """Why a piece of a recording is too short to use (None: it is not): fewer than 2 samples on its grid after
    `data.resample` and `data.stride`, or fewer than `MIN_WINDOW` when latent states are estimated from it."""
    seconds = float(piece.t[-1] - piece.t[0])
    if how.resample:
        n = int(seconds / how.resample + 1e-9) + 1
    else:
        n = piece.n_times
    n = (n - 1) // how.stride + 1
    grid = f"{n} sample{'s' if n != 1 else ''}" + (" on the data.resample grid" if how.resample else "")
    grid += f" after data.stride={how.stride}" if how.stride != 1 else ""
    if n < 2:
        return f"{grid} ({seconds:.4g} s)"
    latent = how.states is not None and any(s not in _observed_names(how) for s in how.states)
    if latent and n < MIN_WINDOW:
        return f"{grid}, fewer than the {MIN_WINDOW} a latent state's estimate needs"
    return None


def _observed_names(how: Recordings) -> list[str]:
    if how.observed:
        return list(how.observed)
    return list(how.outputs) if how.outputs else list(how.states or [])


#: an input whose samples repeat the one before this often is a staircase (a DAC's held output)
STAIRCASE_REPEATS = 0.5
#: an input that repeats this seldom and whose second differences are under this share of its first is smooth;
#: held zoh, its steps matter when one sample's change is over `COARSE` of its spread (under ~60 samples a period)
SMOOTH_REPEATS, SMOOTH_RATIO, COARSE = 0.02, 0.5, 0.1


def hold_warnings(rec: Trajectories, hold: str) -> list[str]:
    """What the inputs of one recording as read say against `data.input_hold`: a staircase held `linear`
    (interpolated across every step), or a smooth, band-limited signal sampled coarsely held `zoh` (a step at every
    sample that a fast-sampled signal would not notice)."""
    if rec.u is None or rec.n_times < 4:
        return []
    out = []
    u = rec.u[0, :, 0].double()  # [T, C]
    d1 = u[1:] - u[:-1]
    repeats = (d1 == 0).double().mean(0)  # [C]
    d2 = d1[1:] - d1[:-1]
    step = d1.pow(2).mean(0).sqrt()
    ratio = d2.pow(2).mean(0).sqrt() / step.clamp_min(1e-300)
    coarse = step / u.std(0).clamp_min(1e-300)
    source = Path(str(rec.meta.get("source"))).name
    for c, name in enumerate(rec.control_names):  # a loop over the few inputs
        if hold == "linear" and float(repeats[c]) > STAIRCASE_REPEATS:
            out.append(
                f"{source}: input '{name}' is a staircase ({100 * float(repeats[c]):.0f} % of its samples repeat the "
                "one before), but data.input_hold=linear interpolates across every step. A held (DAC) output is "
                "data.input_hold=zoh."
            )
        smooth = float(repeats[c]) < SMOOTH_REPEATS and float(ratio[c]) < SMOOTH_RATIO
        if hold == "zoh" and smooth and float(coarse[c]) > COARSE:
            out.append(
                f"{source}: input '{name}' changes smoothly at every sample (band-limited: second differences "
                f"{float(ratio[c]):.2f} of its first), but data.input_hold=zoh makes it a step at every sample. A "
                "sampled smooth signal is data.input_hold=linear."
            )
    return out


def _digest(rec: Trajectories) -> str:
    """A fingerprint of a recording's samples (times from its start, states, inputs): copies have the same."""
    h = hashlib.sha256(rec.t.double().numpy().tobytes())
    h.update(rec.x.double().contiguous().numpy().tobytes())
    if rec.u is not None:
        h.update(rec.u.double().contiguous().numpy().tobytes())
    return h.hexdigest()


def _with_latent(rec: Trajectories, how: Recordings) -> Trajectories:
    """`rec` with the model's states that the file lacks estimated (each from the measured state it is the rate of)."""
    if how.states is None or list(how.states) == rec.state_names:
        return rec
    missing = [s for s in how.states if s not in rec.state_names]
    pending = [s for s in missing if how.rates.get(s) not in rec.state_names]  # no rate: the model estimates them
    rated = {s: how.rates[s] for s in missing if s not in pending}
    return estimate_latent(rec, rated, states=list(how.states), pending=pending, model_based=True)


def _refuse_copies(entries: list[dict[str, Any]]) -> None:
    """Two files of one pattern holding the same samples: a copy would sit in training and in test at once."""
    seen: dict[str, str] = {}
    for e in entries:
        first = seen.setdefault(e["digest"], e["file"])
        if first != e["file"]:
            raise DataError(
                f"{e['file']} holds the same samples as {first} (times, states and inputs identical): a copy would "
                "put the same data in training and in test. Remove one of the two, or give a pattern that matches "
                "one of them."
            )


def read_recordings(path: Path, how: Recordings) -> Trajectories:
    """The batch of every recording `path` names (a file or a pattern): their segments of `data.segment`
    seconds, or the whole recordings (pieces between gaps) when they share one length. ``meta['account']`` says
    what became of every file's samples (`mpsim.data.account`); it is also logged."""
    pieces, entries = read_pieces(path, how)
    return batch_of(pieces, entries, path, how)


def read_pieces(
    path: Path, how: Recordings, rows: Sequence[int] | None = None
) -> tuple[list[Trajectories], list[dict[str, Any]]]:
    """Every recording `path` names (a file or a pattern), as pieces on uniform grids (`one_recording`; `rows`: the
    rows of each file to keep), with each file's entry of the account; copies refused."""
    if how.input_hold not in HOLDS:
        raise ConfigError(f"data.input_hold must be one of {list(HOLDS)}; got {how.input_hold!r}.")
    if isinstance(how.stride, bool) or not isinstance(how.stride, int) or how.stride < 1:
        raise ConfigError(f"data.stride must be a whole number >= 1 (keep every k-th sample); got {how.stride!r}.")
    if how.resample is not None:
        check_resample_step(how.resample)
    files = paths_of(path)
    longs = [p for p in files if not is_recording(p)]
    if longs and len(files) > 1:
        raise DataError(
            f"data.path={path} matches {len(files)} files, {longs[0].name} among them an .npz or long CSV; a pattern "
            "reads recordings (wide CSV or .mat files), one per file. Give a batch file by its name."
        )
    pieces: list[Trajectories] = []
    entries: list[dict[str, Any]] = []
    for p in files:  # a loop over the few files
        got, entry = one_recording(p, how, rows)
        pieces += got
        entries.append(entry)
    _refuse_copies(entries)
    if not pieces:
        raise DataError(f"{path}: no piece of any recording holds 2 samples or more between gaps in its clock.")
    for entry in entries:
        entry.pop("digest")
    return pieces, entries


def batch_of(
    pieces: list[Trajectories],
    entries: list[dict[str, Any]],
    path: Path,
    how: Recordings,
    label: str | None = None,
    segment_s: float | None = None,
    whole: bool = False,
) -> Trajectories:
    """The batch of `pieces`: segments of `data.segment` seconds (`segment_s`, default `how.segment`), or the whole
    pieces (`whole`, or no segment length); its ``meta['account']`` (`label`: which part of the data, e.g.
    "test", with `entries`' rows) is logged."""
    seconds = how.segment if segment_s is None else segment_s
    batch = stack_recordings(pieces) if whole or seconds is None else segment(pieces, seconds)
    batch.meta["input_hold"] = how.input_hold
    account = {
        "path": str(path),
        "pattern": is_pattern(path),
        "files": [dict(e, pieces=[dict(p) for p in e["pieces"]]) for e in entries],
        "segment": batch.meta.get("segment"),
        "resample": how.resample,
        "stride": how.stride,
        "input_hold": how.input_hold,
        "inputs_from_spec": bool(not how.controls and how.inputs),
        "inputs": _controls(how),
    }
    if label is not None:
        account["part"] = label
    _add_usage(account, batch.meta.get("usage", []))
    batch.meta["account"] = account
    for line in account_lines(account):
        log.info(line)
    return batch


def take_rows(rec: Trajectories, rows: Sequence[int]) -> Trajectories:
    """The rows [start, stop) of one recording as read (`data.train_range`, `data.test_range`, ...), named in
    the file's terms when they are not there."""
    start, stop = int(rows[0]), int(rows[1])
    if not 0 <= start < stop or stop > rec.n_times:
        raise DataError(
            f"{rec.meta.get('source')}: rows [{start}, {stop}) asked for, but the recording has {rec.n_times} rows "
            f"(0 to {rec.n_times - 1}); give a range within them, start < stop (Python's [start, stop))."
        )
    meta = {**rec.meta, "first_row": int(rec.meta.get("first_row", 0)) + start}
    u = None if rec.u is None else rec.u[:, start:stop]
    return replace(rec, t=rec.t[start:stop], x=rec.x[:, start:stop], u=u, meta=meta)


def _add_usage(account: dict[str, Any], usage: list[dict[str, Any]]) -> None:
    """Each piece's segments and unused samples (from `segment` / `stack_recordings`), into the account."""
    by_piece = {(u["recording"], int(u.get("piece", 1))): u for u in usage}
    for entry in account["files"]:
        for part in entry["pieces"]:
            use = by_piece.get((entry["file"], part["piece"]))
            if use is not None:
                part.update({k: v for k, v in use.items() if k not in ("recording", "piece")})
