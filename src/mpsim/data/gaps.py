"""Gaps in a recording's clock: a step much longer than the others (a logger that stopped, dropped packets) splits
the recording into pieces, each its own stretch of data; a short gap may be filled by interpolation, but only when
`data.resample` interpolates anyway, and the report names every gap filled.

A step longer than `GAP_STEPS` median steps is a gap (the 5 % jitter a recording may have on its own grid is far
below). With `data.resample`, gaps of at most `FILL_STEPS` median steps (one or two lost samples) are filled by the
resampling's linear interpolation; longer ones split. Without `data.resample` every gap splits: a recording is
used on its own grid, which a gap would break. Pieces of fewer than 2 samples are kept out, named.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import torch

from mpsim.data.trajectories import Trajectories

#: a step longer than this many median steps is a gap
GAP_STEPS = 1.5
#: with `data.resample`, a gap of at most this many median steps is filled by interpolation (and named); longer split
FILL_STEPS = 3.0


def split_at_gaps(rec: Trajectories, fill: bool) -> tuple[list[Trajectories], list[dict[str, Any]]]:
    """The pieces of `rec` between its gaps, and one record per gap.

    Args:
        rec: [1, T, N, D] one recording, times from its first sample (``meta['t0']``: the file's first time).
        fill: `data.resample` is on: gaps of at most `FILL_STEPS` median steps stay inside a piece (filled).

    Returns:
        The pieces of 2 samples or more in time order (each with ``meta['piece']`` = k of ``meta['pieces']``,
        1-based, when there are several), and for each gap ``{"t": <file time of the sample before>, "seconds",
        "steps", "row", "action": "split" | "filled"}`` (row: the 0-based index of the sample after the gap); a
        single sample between two gaps (or before the first, after the last) is listed under its gap's ``"alone"``.
    """
    t = rec.t.double()
    steps = t[1:] - t[:-1]  # [T - 1]
    if len(steps) == 0:
        return [rec], []
    median = float(steps.median())
    ratio = steps / median
    at = torch.nonzero(ratio > GAP_STEPS).flatten().tolist()
    if not at:
        return [rec], []
    origin = float(rec.meta.get("t0", [0.0])[0])
    gaps = []
    cuts = []
    for k in at:  # a loop over the few gaps
        action = "filled" if fill and float(ratio[k]) <= FILL_STEPS else "split"
        gaps.append(
            {
                "t": origin + float(t[k]),
                "seconds": float(steps[k]),
                "steps": float(ratio[k]),
                "row": int(rec.meta.get("first_row", 0)) + k + 1,
                "action": action,
            }
        )
        if action == "split":
            cuts.append(k + 1)
    if not cuts:
        return [rec], gaps
    bounds = [0, *cuts, rec.n_times]
    pieces = []
    for j in range(len(bounds) - 1):  # a loop over the few pieces
        start, stop = bounds[j], bounds[j + 1]
        first = int(rec.meta.get("first_row", 0)) + start
        meta = {**rec.meta, "piece": j + 1, "pieces": len(bounds) - 1, "first_row": first}
        if stop - start < 2:  # a single sample between gaps: no trajectory, only its place in the account
            gaps[j - 1 if j else 0].setdefault("alone", []).append(
                {"piece": j + 1, "row": first, "t": origin + float(t[start])}
            )
            continue
        pieces.append(
            replace(
                rec,
                t=rec.t[start:stop],
                x=rec.x[:, start:stop],
                u=None if rec.u is None else rec.u[:, start:stop],
                meta=meta,
            )
        )
    return pieces, gaps


def piece_name(meta: dict[str, Any], name: str) -> str:
    """How messages name a piece of a recording: "rec.csv part 2 of 3" (or just the recording's `name`)."""
    if int(meta.get("pieces", 1)) > 1:
        return f"{name} part {meta['piece']} of {meta['pieces']}"
    return name
