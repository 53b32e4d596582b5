"""From recordings to one batch: `segment` (`data.segment=<seconds>`), `stack_recordings` (whole recordings, one
trajectory each) and `contiguous_split` (train, validation and test as contiguous blocks in time).

The batch's time grid ``t`` is relative (it starts at 0). ``meta['segments']`` lists, in batch order (recording,
then time), ``{"recording": <source>, "index": k, "t0": <absolute start time>}``: a sample's absolute time is
t0 + t.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from mpsim.data.dataset import SPLITS, Splits, split_sizes
from mpsim.data.trajectories import Trajectories, grid_step
from mpsim.errors import ConfigError, DataError

#: recordings share a step when theirs differ by less than this share of it
DT_RTOL = 1e-6


def segment(recs: Sequence[Trajectories], seconds: float) -> Trajectories:
    """Every recording cut into consecutive segments of L + 1 samples, L = round(seconds / dt), stacked as a batch.

    Segment k of a recording covers its samples kL .. (k+1)L (neighbours share their end sample); the incomplete
    tail is dropped, and a recording shorter than one segment is skipped (named in ``meta['skipped']``).

    Args:
        recs: recordings (each [1, T_r, N, D], B = 1) on uniform grids of one step (after `data.resample`), with
            the same state and input names.
        seconds: `data.segment`, the length of a segment in seconds.

    Returns:
        [S, L + 1, N, D] for the S segments of all recordings, in recording then time order.
    """
    dt = _common_step(recs)
    if not (math.isfinite(seconds) and seconds > 0):
        raise ConfigError(f"data.segment must be a length in seconds > 0; got {seconds}.")
    n = round(seconds / dt)
    if n < 1:
        raise ConfigError(f"data.segment={seconds:g} s is shorter than one sampling step ({dt:g} s); make it longer.")
    parts: list[Trajectories] = []
    entries: list[dict[str, Any]] = []
    skipped: list[dict[str, Any]] = []
    for rec in recs:  # a loop over the few recordings; each is cut with one unfold
        count = (rec.n_times - 1) // n
        source = str(rec.meta.get("source", rec.system_name))
        if count == 0:
            skipped.append({"recording": source, "seconds": float(rec.t[-1] - rec.t[0])})
            continue
        parts.append(_windows(rec, n, count))
        t0 = rec.t.double()[0] + dt * n * torch.arange(count, dtype=torch.float64)
        entries += [{"recording": source, "index": k, "t0": float(t0[k])} for k in range(count)]
    if not parts:
        longest = max(float(r.t[-1] - r.t[0]) for r in recs)
        raise DataError(
            f"{_names(recs)}: data.segment={seconds:g} s is longer than every recording (the longest lasts "
            f"{longest:g} s); use a shorter segment."
        )
    meta = {**_batch_meta(recs, dt), "segments": entries, "segment": float(seconds), "skipped": skipped}
    return _stack(parts, n + 1, dt, meta)


def stack_recordings(recs: Sequence[Trajectories]) -> Trajectories:
    """Whole recordings as the batch, one trajectory each (no `data.segment`): they must share their step and
    their length (after `data.resample` / `data.stride`)."""
    dt = _common_step(recs)
    lengths = {str(r.meta.get("source", r.system_name)): r.n_times for r in recs}
    if len(set(lengths.values())) > 1:
        raise DataError(
            f"recordings of different lengths {lengths} (samples) cannot be one batch of whole trajectories. Cut "
            "them into segments of one length with data.segment=<seconds> (e.g. data.segment=1.0)."
        )
    entries = [{"recording": src, "index": 0, "t0": float(r.t[0])} for src, r in zip(lengths, recs, strict=True)]
    return _stack(list(recs), recs[0].n_times, dt, {**_batch_meta(recs, dt), "segments": entries})


def _windows(rec: Trajectories, n: int, count: int) -> Trajectories:
    """The `count` windows of n + 1 samples starting every n samples of the single trajectory `rec`."""

    def cut(a: torch.Tensor) -> torch.Tensor:  # a: [1, T, N, K] -> [count, n + 1, N, K]
        return a[0, : count * n + 1].unfold(0, n + 1, n).permute(0, 3, 1, 2)

    t = rec.t[: n + 1] - rec.t[0]
    return Trajectories(t=t, x=cut(rec.x), edge_index=rec.edge_index, u=None if rec.u is None else cut(rec.u))


def _stack(parts: list[Trajectories], length: int, dt: float, meta: dict[str, Any]) -> Trajectories:
    first = parts[0]
    u = None if first.u is None else torch.cat([p.u for p in parts if p.u is not None])
    return Trajectories(
        t=dt * torch.arange(length, dtype=first.t.dtype),
        x=torch.cat([p.x for p in parts]).contiguous(),
        edge_index=first.edge_index,
        u=None if u is None else u.contiguous(),
        meta=meta,
    )


def _common_step(recs: Sequence[Trajectories]) -> float:
    """The step all `recs` share on uniform grids, with the same states and inputs; else one message."""
    if not recs:
        raise DataError("no recordings to make a batch of (data.path matched no file).")
    steps = {str(r.meta.get("source", r.system_name)): grid_step(r.t) for r in recs}
    uneven = [src for src, dt in steps.items() if not math.isfinite(dt)]
    if uneven:
        raise DataError(
            f"{uneven[0]}: the sampling is not uniform, so it cannot be cut into segments of one time grid. "
            "Interpolate onto a uniform grid with data.resample=<dt>."
        )
    (src0, dt0), *others = steps.items()
    for src, dt in others:
        if abs(dt - dt0) > DT_RTOL * dt0:
            raise DataError(
                f"{src} is sampled every {dt:.6g} s but {src0} every {dt0:.6g} s; one batch needs one step. Put "
                f"every file on one grid with data.resample=<dt>, e.g. data.resample={max(dt, dt0):.2g}."
            )
    for rec in recs[1:]:
        names = (rec.state_names, rec.control_names, rec.n_nodes)
        if names != (recs[0].state_names, recs[0].control_names, recs[0].n_nodes):
            raise DataError(
                f"{rec.meta.get('source')} holds states {rec.state_names} and inputs {rec.control_names} but "
                f"{recs[0].meta.get('source')} holds {recs[0].state_names} and {recs[0].control_names}."
            )
    return float(sum(steps.values()) / len(steps))


def _batch_meta(recs: Sequence[Trajectories], dt: float) -> dict[str, Any]:
    """The metadata a batch keeps of its recordings: the first one's, less what belongs to one file."""
    per_file = ("source", "system", "t0", "jitter")
    meta = {k: v for k, v in recs[0].meta.items() if k not in per_file}
    sources = [str(r.meta.get("source", r.system_name)) for r in recs]
    systems = {r.system_name for r in recs}
    meta.update(
        system=systems.pop() if len(systems) == 1 else "recordings",
        source=_names(recs),
        sources=sources,
        dt=dt,
    )
    return meta


def _names(recs: Sequence[Trajectories]) -> str:
    names = [str(r.meta.get("source", r.system_name)) for r in recs]
    return ", ".join(names) if len(names) <= 3 else f"{names[0]} and {len(names) - 1} more files"


def contiguous_split(data: Trajectories, fractions: Sequence[float], need: tuple[str, ...] = SPLITS) -> Splits:
    """Train, validation and test as contiguous blocks of the batch (`segment`'s order: recording, then time):
    the first share trains, the next validates, the last tests, so no test segment lies between two training
    ones. Shares as `mpsim.data.dataset.split_trajectories` (`data.split`; normalised, each split in `need` gets
    at least one segment). Each split's ``meta['covers']`` says which recordings and times it holds
    ("ddp_500Hz.csv 0–4 s, direct_collocation_333Hz.csv 0–2 s"), ``meta['segments']`` its own entries.
    """
    b = len(data)
    sizes = split_sizes(b, fractions, need, "segments")
    if sizes is None:
        raise DataError(
            f"{data.meta.get('source', 'data')}: {b} segments cannot be split into train/val/test {list(fractions)} "
            f"with at least one each; use a shorter data.segment or more recordings."
        )
    bounds = [0, sizes[0], sizes[0] + sizes[1], b]
    out = [_block(data, bounds[i], bounds[i + 1]) for i in range(3)]
    return Splits(train=out[0], val=out[1], test=out[2])


def _block(data: Trajectories, start: int, stop: int) -> Trajectories:
    """The segments start..stop−1 with their own metadata (``segments``, ``covers``)."""
    entries = list(data.meta.get("segments", []))[start:stop]
    part = data.subset(list(range(start, stop)))
    seconds = float(data.t[-1] - data.t[0])
    part.meta = {**data.meta, "segments": entries, "covers": covers(entries, seconds)}
    return part


def covers(entries: Sequence[dict[str, Any]], seconds: float) -> str:
    """What segments cover, per recording, as the summary says it: "ddp_500Hz.csv 0–4 s, dircol.csv 2–3.5 s"
    (contiguous segments merged; `seconds`: one segment's length)."""
    spans: list[list[Any]] = []  # [name, start, end]
    for e in entries:
        name, start = Path(str(e["recording"])).name, float(e["t0"])
        if spans and spans[-1][0] == name and abs(spans[-1][2] - start) <= 1e-6 * max(seconds, 1e-12):
            spans[-1][2] = start + seconds
        else:
            spans.append([name, start, start + seconds])
    return ", ".join(f"{name} {start:.4g}–{end:.4g} s" for name, start, end in spans) or "nothing"
