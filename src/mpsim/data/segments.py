"""From recordings to one batch: `segment` (`data.segment=<seconds>`), `stack_recordings` (whole recordings, one
trajectory each) and `contiguous_split` (train, validation and test as contiguous blocks in time).

The batch's time grid ``t`` is relative (it starts at 0). ``meta['segments']`` lists, in batch order (recording,
then time), ``{"recording": <source>, "piece": p, "index": k, "t0": <the file's time at its start>}``: a sample's
time in its file is t0 + t. ``meta['usage']`` says, per recording (or piece of one, between gaps), how many
segments it gave and how many of its samples they use.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from mpsim.data.dataset import SPLITS, Splits, split_sizes
from mpsim.data.trajectories import Trajectories, grid_step
from mpsim.errors import ConfigError, DataError

#: recordings share a step when theirs differ by less than this share of it
DT_RTOL = 1e-6
#: a segment, rounded to whole steps, may differ from `data.segment` by at most this share of it
SEGMENT_RTOL = 0.01


def segment(recs: Sequence[Trajectories], seconds: float) -> Trajectories:
    """Every recording cut into consecutive segments of L + 1 samples, L = round(seconds / dt), stacked as a batch.

    Segment k of a recording covers its samples kL .. (k+1)L (neighbours share their end sample); the incomplete
    tail is dropped, and a recording shorter than one segment is skipped (named in ``meta['skipped']``; both are
    counted in ``meta['usage']``). A length that is not a whole number of steps within `SEGMENT_RTOL` is refused
    with the two nearest that are.

    Args:
        recs: recordings (each [1, T_r, N, D], B = 1) on uniform grids of one step (after `data.resample`), with
            the same state and input names.
        seconds: `data.segment`, the length of a segment in seconds.

    Returns:
        [S, L + 1, N, D] for the S segments of all recordings, in recording then time order.
    """
    dt = _common_step(recs)
    if (
        isinstance(seconds, bool)
        or not isinstance(seconds, int | float)
        or not (math.isfinite(seconds) and seconds > 0)
    ):
        raise ConfigError(f"data.segment must be a length in seconds > 0; got {seconds!r}.")
    longest = max(float(r.t[-1] - r.t[0]) for r in recs)
    if seconds > longest + 0.5 * dt:
        raise DataError(
            f"{_names(recs)}: data.segment={seconds:g} s is longer than every recording (the longest lasts "
            f"{longest:g} s{_sampled(recs, dt)}); use a shorter segment."
        )
    n = whole_steps(seconds, dt, recs)
    parts: list[Trajectories] = []
    entries: list[dict[str, Any]] = []
    skipped: list[dict[str, Any]] = []
    usage: list[dict[str, Any]] = []
    for rec in recs:  # a loop over the few recordings; each is cut with one unfold
        count = (rec.n_times - 1) // n
        source = str(rec.meta.get("source", rec.system_name))
        piece = int(rec.meta.get("piece", 1))
        used = count * n + 1 if count else 0
        usage.append({"recording": source, "piece": piece, "segments": count, "used": used, "samples": rec.n_times})
        if count == 0:
            skipped.append({"recording": source, "piece": piece, "seconds": float(rec.t[-1] - rec.t[0])})
            continue
        parts.append(_windows(rec, n, count))
        t0 = _origin(rec) + rec.t.double()[0] + dt * n * torch.arange(count, dtype=torch.float64)
        entries += [{"recording": source, "piece": piece, "index": k, "t0": float(t0[k])} for k in range(count)]
    if not parts:
        raise DataError(
            f"{_names(recs)}: data.segment={seconds:g} s is longer than every recording (the longest lasts "
            f"{longest:g} s{_sampled(recs, dt)}); use a shorter segment."
        )
    meta = {
        **_batch_meta(recs, dt),
        "segments": entries,
        "segment": float(n * dt),
        "skipped": skipped,
        "usage": usage,
    }
    return _stack(parts, n + 1, dt, meta)


def whole_steps(seconds: float, dt: float, recs: Sequence[Trajectories] = ()) -> int:
    """`data.segment` as a whole number of steps of `dt` (at least 1): refused, with the two nearest lengths
    that are, when rounding would change it by more than `SEGMENT_RTOL`."""
    n = max(1, round(seconds / dt))
    if abs(n * dt - seconds) > SEGMENT_RTOL * seconds:
        low, high = max(1, math.floor(seconds / dt)), math.ceil(seconds / dt)
        choices = sorted({low, high, n})
        shown = " or ".join(f"data.segment={k * dt:.6g}" for k in choices)
        raise ConfigError(
            f"data.segment={seconds:g} s is {seconds / dt:.4g} steps of {dt:g} s{_sampled(recs, dt)}; a segment is a "
            f"whole number of steps, and the nearest ({n * dt:.6g} s) differs by "
            f"{100 * abs(n * dt - seconds) / seconds:.3g} %. Use {shown}."
        )
    return n


def _sampled(recs: Sequence[Trajectories], dt: float) -> str:
    """How the step came about, for messages: ", sampled every 1.5 s after data.stride=30"."""
    if not recs:
        return ""
    k = int(recs[0].meta.get("stride", 1))
    return f" after data.stride={k}" if k > 1 else ""


def _origin(rec: Trajectories) -> float:
    """The file's time of a recording's time 0 (its first sample's, ``meta['t0']``)."""
    t0 = rec.meta.get("t0", [0.0])
    return float(t0[0]) if isinstance(t0, list | tuple) and t0 else 0.0


def stack_recordings(recs: Sequence[Trajectories]) -> Trajectories:
    """Whole recordings as the batch, one trajectory each (no `data.segment`): they must share their step and
    their length (after `data.resample` / `data.stride`)."""
    dt = _common_step(recs)
    names = [_piece_name(r) for r in recs]
    lengths = {name: r.n_times for name, r in zip(names, recs, strict=True)}
    if len(set(lengths.values())) > 1:
        split = any(int(r.meta.get("pieces", 1)) > 1 for r in recs)
        why = " (a gap in a recording's clock splits it into parts)" if split else ""
        raise DataError(
            f"recordings of different lengths {lengths} (samples){why} cannot be one batch of whole trajectories. "
            "Cut them into segments of one length with data.segment=<seconds> (e.g. data.segment=1.0)."
        )
    entries, usage = [], []
    for r in recs:
        source, piece = str(r.meta.get("source", r.system_name)), int(r.meta.get("piece", 1))
        entries.append({"recording": source, "piece": piece, "index": 0, "t0": _origin(r) + float(r.t[0])})
        usage.append({"recording": source, "piece": piece, "segments": 1, "used": r.n_times, "samples": r.n_times})
    meta = {**_batch_meta(recs, dt), "segments": entries, "usage": usage}
    return _stack(list(recs), recs[0].n_times, dt, meta)


def _piece_name(rec: Trajectories) -> str:
    name = Path(str(rec.meta.get("source", rec.system_name))).name
    pieces = int(rec.meta.get("pieces", 1))
    return f"{name} part {rec.meta.get('piece')} of {pieces}" if pieces > 1 else name


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
    per_file = ("source", "system", "t0", "jitter", "piece", "pieces", "first_row", "rows", "time_origin")
    meta = {k: v for k, v in recs[0].meta.items() if k not in per_file}
    sources = list(dict.fromkeys(str(r.meta.get("source", r.system_name)) for r in recs))
    systems = {r.system_name for r in recs}
    meta.update(
        system=systems.pop() if len(systems) == 1 else "recordings",
        source=_names(recs),
        sources=sources,
        dt=dt,
    )
    return meta


def _names(recs: Sequence[Trajectories]) -> str:
    names = list(dict.fromkeys(str(r.meta.get("source", r.system_name)) for r in recs))
    return ", ".join(names) if len(names) <= 3 else f"{names[0]} and {len(names) - 1} more files"


def contiguous_split(data: Trajectories, fractions: Sequence[float], need: tuple[str, ...] = SPLITS) -> Splits:
    """Train, validation and test as contiguous blocks of the batch (`segment`'s order: recording, then time):
    the first share trains, the next validates, the last tests, so no test segment lies between two training
    ones. Shares as `mpsim.data.dataset.split_trajectories` (`data.split`; normalised, each split in `need` gets
    at least one segment). Each split's ``meta['covers']`` says which recordings and times it holds
    ("ddp_500Hz.csv 0–4 s, direct_collocation_333Hz.csv 0–2 s"), ``meta['segments']`` its own entries.
    """
    b = len(data)
    kind = "segments" if data.meta.get("segment") is not None else "recordings"
    sizes = split_sizes(b, fractions, need, kind)
    if sizes is None:
        fix = (
            "use a shorter data.segment or more recordings"
            if kind == "segments"
            else "cut the recordings into segments with data.segment=<seconds>, or give more recordings"
        )
        raise DataError(
            f"{data.meta.get('source', 'data')}: {b} {kind} cannot be split into train/val/test {list(fractions)} "
            f"with at least one each; {fix}."
        )
    bounds = [0, sizes[0], sizes[0] + sizes[1], b]
    out = [_block(data, bounds[i], bounds[i + 1]) for i in range(3)]
    records = whole_records(stitch(out[2])) if len(out[2]) else None
    return Splits(train=out[0], val=out[1], test=out[2], records=records)


def _block(data: Trajectories, start: int, stop: int) -> Trajectories:
    """The segments start..stop−1 with their own metadata (``segments``, ``covers``)."""
    entries = list(data.meta.get("segments", []))[start:stop]
    part = data.subset(list(range(start, stop)))
    seconds = float(data.t[-1] - data.t[0])
    origins = {f["file"]: f["span"][0] for f in data.meta.get("account", {}).get("files", [])}
    part.meta = {**data.meta, "segments": entries, "covers": covers(entries, seconds, origins)}
    return part


#: file times at least this large (seconds since 1970, say) are shown from the recording's first sample
LARGE_TIME = 1e5


def covers(entries: Sequence[dict[str, Any]], seconds: float, origins: Mapping[str, float] | None = None) -> str:
    """What segments cover, per recording, as the summary says it: "ddp_500Hz.csv 0–4 s, dircol.csv 2–3.5 s"
    (contiguous segments merged; `seconds`: one segment's length). Times are the file's own; where they are large
    (`LARGE_TIME`: a clock since 1970) they are counted from the recording's first sample, `origins`
    ({recording: its first time}), and say so."""
    spans: list[list[Any]] = []  # [name, start, end, origin]
    for e in entries:
        name, start = Path(str(e["recording"])).name, float(e["t0"])
        origin = (origins or {}).get(str(e["recording"]), 0.0)
        if spans and spans[-1][0] == name and abs(spans[-1][2] - start) <= 1e-6 * max(seconds, 1e-12):
            spans[-1][2] = start + seconds
        else:
            spans.append([name, start, start + seconds, origin])
    parts = []
    for name, start, end, origin in spans:
        if abs(start) <= 1e-6 * max(seconds, 1e-12):  # a grid fitted to rounded times starts a hair off zero
            start = 0.0
        if max(abs(start), abs(end)) >= LARGE_TIME:
            parts.append(f"{name} {start - origin:.4g}–{end - origin:.4g} s from its start")
        else:
            parts.append(f"{name} {start:.4g}–{end:.4g} s")
    return ", ".join(parts) or "nothing"


def whole_records(recs: Sequence[Trajectories]) -> Trajectories:
    """The recordings (or pieces, or stitched test segments) as one batch of whole records for free-run
    evaluation: [R, T_max, N, D], each padded after its end with its last sample (states and inputs: a rollout
    past the end stays finite; scores read only the first `length` samples). ``meta['records']`` lists per record
    its recording, piece, start time t0 in the file's clock and length in samples."""
    dt = _common_step(recs)
    length = max(r.n_times for r in recs)
    xs, us, entries = [], [], []
    for r in recs:  # a loop over the few records
        pad = length - r.n_times
        xs.append(torch.cat([r.x, r.x[:, -1:].expand(1, pad, *r.x.shape[2:])], dim=1))
        if r.u is not None:
            us.append(torch.cat([r.u, r.u[:, -1:].expand(1, pad, *r.u.shape[2:])], dim=1))
        entries.append(
            {
                "recording": str(r.meta.get("source", r.system_name)),
                "piece": int(r.meta.get("piece", 1)),
                "t0": _origin(r) + float(r.t[0]),
                "length": r.n_times,
            }
        )
    meta = {**_batch_meta(recs, dt), "records": entries}
    return Trajectories(
        t=dt * torch.arange(length, dtype=recs[0].t.dtype),
        x=torch.cat(xs).contiguous(),
        edge_index=recs[0].edge_index,
        u=torch.cat(us).contiguous() if us else None,
        meta=meta,
    )


def stitch(part: Trajectories) -> list[Trajectories]:
    """The records a split of segments holds: each run of consecutive segments of one recording (piece) joined
    back into one trajectory (neighbours share their end sample), as [1, T_r, N, D] recordings whose times run from
    their first sample and whose ``meta['t0']`` is its time in the file's clock."""
    entries = list(part.meta.get("segments", []))
    if not entries:
        return []
    runs: list[list[int]] = []
    for i, e in enumerate(entries):
        prev = entries[i - 1] if i else {}
        same = bool(prev) and (prev["recording"], prev.get("piece", 1)) == (e["recording"], e.get("piece", 1))
        if same and int(e["index"]) == int(prev["index"]) + 1:
            runs[-1].append(i)
        else:
            runs.append([i])
    out = []
    length = part.n_times - 1
    for run in runs:  # a loop over the few runs
        idx = torch.as_tensor(run)
        body = part.x[idx, :-1].reshape(1, -1, *part.x.shape[2:])
        x = torch.cat([body, part.x[run[-1] : run[-1] + 1, -1:]], dim=1)
        u = None
        if part.u is not None:
            ubody = part.u[idx, :-1].reshape(1, -1, *part.u.shape[2:])
            u = torch.cat([ubody, part.u[run[-1] : run[-1] + 1, -1:]], dim=1)
        first = entries[run[0]]
        meta = {
            **{k: v for k, v in part.meta.items() if k not in ("segments", "covers", "usage", "skipped")},
            "source": first["recording"],
            "piece": int(first.get("piece", 1)),
            "t0": [float(first["t0"])],
        }
        t = float(part.meta.get("dt", float(part.t[1] - part.t[0]))) * torch.arange(
            len(run) * length + 1, dtype=part.t.dtype
        )
        out.append(Trajectories(t=t, x=x, edge_index=part.edge_index, u=u, meta=meta))
    return out
