"""Samples a sensor clipped (issue 72, item 2): runs of one identical extreme value — a level sensor that reads
10.000 V for forty samples at every overflow, an encoder at its end stop. No dynamics gives a flat top; a fit
would bend the model towards it. Found per recording and measured channel as read, before any resampling.

A channel is called clipped when it holds its own maximum (or minimum) exactly for `MIN_RUN` samples or more in a
row, in at least `MIN_RUNS` separate runs or in one run of `LONG_RUN` samples or more, and the signal steps onto
or off those runs by more than `STEP_FACTOR` times its finest step (the larger median of the two sides): a finely quantised smooth signal also holds
its top value for a few samples at every peak, but it creeps onto it one quantisation step at a time.
"""

from __future__ import annotations

from typing import Any

import torch

#: a run of identical samples shorter than this is no clip (a quantised peak)
MIN_RUN = 3
#: ... and the extreme value held in at least this many separate runs (a clip recurs at every overshoot)
MIN_RUNS = 2
#: ... or in one run at least this long
LONG_RUN = 10
#: the median step onto or off the runs (the larger) must exceed this many times the channel's finest nonzero step
STEP_FACTOR = 3.0


def clipped_channels(
    x: torch.Tensor,  # [T, D] one recording's measured channels as read
    names: list[str],  # D channel names
) -> list[dict[str, Any]]:
    """[{"channel", "side" ("max"/"min"), "value", "runs", "samples", "share"}] of every channel held at its own
    extreme in runs of identical samples (`MIN_RUN`, `MIN_RUNS`, `LONG_RUN`)."""
    out = []
    n = x.shape[0]
    for d, name in enumerate(names):  # the few measured channels
        v = x[:, d]
        if n < MIN_RUN or not bool(torch.isfinite(v).all()) or float(v.max()) == float(v.min()):
            continue
        for side, value in (("max", v.max()), ("min", v.min())):  # the two extremes
            at = torch.cat([torch.zeros(1, dtype=torch.bool), v == value, torch.zeros(1, dtype=torch.bool)])
            edges = torch.nonzero(at[1:].int() - at[:-1].int()).flatten()  # starts and ends of the runs, paired
            starts, ends = edges[0::2], edges[1::2]
            keep = (ends - starts) >= MIN_RUN
            long = (ends - starts)[keep]
            if not (long.numel() >= MIN_RUNS or (long.numel() and int(long.max()) >= LONG_RUN)):
                continue
            if _steps_onto(v, starts[keep], ends[keep], value) <= STEP_FACTOR * _finest_step(v):
                continue  # crept onto its extreme: a quantised smooth peak
            samples = int(long.sum())
            out.append(
                {"channel": name, "side": side, "value": float(value), "runs": int(long.numel()),
                 "samples": samples, "share": samples / n}
            )  # fmt: skip
    return out


def _finest_step(v: torch.Tensor) -> float:  # v: [T]
    steps = (v[1:] - v[:-1]).abs()
    steps = steps[steps > 0]
    return float(steps.min()) if steps.numel() else 0.0


def _steps_onto(v: torch.Tensor, starts: torch.Tensor, ends: torch.Tensor, value: torch.Tensor) -> float:
    """The larger of the median step onto (from the sample before) and the median step off (to the sample after)
    the runs [starts, ends): a clip is left or entered steeply on at least one side."""
    before = (v[starts[starts > 0] - 1] - value).abs()
    after = (v[ends[ends < v.numel()]] - value).abs()
    return max([float(s.median()) for s in (before, after) if s.numel()], default=0.0)


def clipped_text(entry: dict[str, Any]) -> str:
    """One line on a clipped channel, and what is done with its samples."""
    return (
        f"{entry['channel']} reads its {'maximum' if entry['side'] == 'max' else 'minimum'} {entry['value']:.6g} in "
        f"{entry['runs']} run{'s' if entry['runs'] != 1 else ''} of {MIN_RUN} or more identical samples "
        f"({entry['samples']} samples, {100 * entry['share']:.2g} %): clipped by the sensor, or a flat top no "
        "dynamics gives. They are fitted as they are (not skipped, no clip modelled): check the sensor's range, "
        "or leave those rows out (data.train_range / data.test_range)"
    )
