"""A benchmark's own split of its recordings: by file (`data.path` to train, `data.test_path` to test) and by sample
range within the records (`data.train_range`, `data.val_range`, `data.test_range`: rows [start, stop) of every file,
as the file has them, before `data.resample` / `data.stride`).

Training data are cut into segments (`data.segment`) as usual. The test records are kept whole
(`Splits.records`), for free-run evaluation from their first samples to their end; the test split scored every
epoch (and held out by `mpsim diagnose`) holds their segments, or the records whole when they are shorter than a
segment and share a length. Validation comes
from `data.val_range`; else, with `data.test_path` and no ranges, from the end of `data.path`'s segments
(`data.split`'s first two shares); else it is the training data itself, and the summary says so.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from mpsim.data.dataset import SPLITS, Splits
from mpsim.data.measured import Recordings, batch_of, read_pieces
from mpsim.data.segments import contiguous_split, covers, whole_records
from mpsim.data.trajectories import Trajectories
from mpsim.errors import ConfigError, DataError

RANGE_KEYS = ("train_range", "val_range", "test_range")


def check_range(key: str, rows: Any) -> tuple[int, int] | None:
    """`data.<key>` as (start, stop) rows, or None; one message for anything else."""
    if rows is None:
        return None
    ok = isinstance(rows, list | tuple) and len(rows) == 2
    ok = ok and all(isinstance(r, int) and not isinstance(r, bool) for r in rows) and 0 <= rows[0] < rows[1]
    if not ok:
        raise ConfigError(
            f"data.{key}={rows}: give the rows [start, stop) of every file to use, whole numbers with 0 <= start < "
            f"stop, e.g. data.{key}=[0,400] (rows as the file has them, before data.resample and data.stride)."
        )
    return int(rows[0]), int(rows[1])


def official_splits(
    path: Path,
    test_path: Path | None,
    ranges: dict[str, tuple[int, int] | None],
    how: Recordings,
    fractions: Sequence[float],
    need: tuple[str, ...] = SPLITS,
) -> Splits:
    """Train, validation and test of recordings split by file and/or by row range (module docstring).

    Args:
        path, test_path: `data.path` and `data.test_path` (resolved; test_path None: test rows come from path).
        ranges: {"train_range": rows or None, "val_range": ..., "test_range": ...}.
        how: how recordings become a batch (`mpsim.data.measured.Recordings`).
        fractions: `data.split`; only its first two shares are read, when validation comes from `path`'s end.
        need: the splits the command uses (`mpsim eval`: the test split alone).
    """
    if test_path is None and ranges["test_range"] is None:
        raise ConfigError(
            "data.train_range / data.val_range need a test part: give data.test_range=[start,stop] (rows of the "
            "same files) or data.test_path=<file or pattern>."
        )
    tests, test_entries = read_pieces(test_path or path, how, ranges["test_range"])
    test = _test_batch(tests, test_entries, test_path or path, how)
    test.meta["covers"] = records_covers(test_entries)
    records = whole_records(tests)
    if need == ("test",):
        empty = test.subset([])
        return Splits(train=empty, val=empty, test=test, records=records)
    pieces, entries = read_pieces(path, how, ranges["train_range"])
    train = batch_of(pieces, entries, path, how, "train")
    if ranges["val_range"] is not None:
        vals, val_entries = read_pieces(path, how, ranges["val_range"])
        val = batch_of(vals, val_entries, path, how, "val")
    elif test_path is not None and ranges["train_range"] is None and "segments" in train.meta:
        shares = [float(fractions[0]), float(fractions[1]), 0.0]
        parts = contiguous_split(train, shares, ("train", "val"))
        train, val = parts.train, parts.val
    else:
        val = train.subset(list(range(len(train))))
        val.meta = {**train.meta, "covers": "the training data (no data.val_range)"}
    if "covers" not in train.meta:
        segments = train.meta.get("segments")
        seconds = float(train.t[-1] - train.t[0])
        train.meta["covers"] = covers(segments, seconds) if segments else records_covers(entries)
    return Splits(train=train, val=val, test=test, records=records)


def _test_batch(pieces: list[Trajectories], entries: list[dict[str, Any]], path: Path, how: Recordings) -> Trajectories:
    """The test split scored every epoch (and held out by `mpsim diagnose`): the test records' segments of
    `data.segment`; the records whole when they are shorter than a segment (or none is given) and share a length."""
    same = len({p.n_times for p in pieces}) == 1
    fits = how.segment is not None and any(float(p.t[-1] - p.t[0]) >= how.segment for p in pieces)
    if not same and not fits:
        lengths = {Path(str(p.meta.get("source"))).name: p.n_times for p in pieces}
        raise DataError(
            f"the test records differ in length {lengths} (samples); give data.segment=<seconds> so that their "
            "windows can be scored every epoch (free-run evaluation still simulates each record whole)."
        )
    return batch_of(pieces, entries, path, how, "test", whole=not fits)


def records_covers(entries: Sequence[dict[str, Any]]) -> str:
    """What whole records cover, per file: "ced_unif_1.csv rows 400–499 (8–9.98 s)"."""
    parts = []
    for e in entries:
        name = Path(str(e["file"])).name
        rows = f"rows {e['range'][0]}–{e['range'][1] - 1} " if "range" in e else ""
        parts.append(f"{name} {rows}({e['span'][0]:.4g}–{e['span'][1]:.4g} s)")
    return ", ".join(parts) or "nothing"
