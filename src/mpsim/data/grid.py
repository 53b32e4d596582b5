"""Time-grid steps on measured recordings: `resample` (`data.resample`), `stride` (`data.stride`) and
`uniform_or_refuse` (a recording used on its own grid).

Each takes a `Trajectories` and returns a new one (the input is not changed); they work on any B and N, a recording
(B = N = 1) being the usual case. Times stay absolute.
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch

from mpsim.data.trajectories import Trajectories
from mpsim.errors import ConfigError, DataError

#: the largest distance of a sample time from the uniform grid closest to the times, as a share of the step, that
#: `uniform_or_refuse` accepts. Snapping a sample onto the grid moves its reading by at most
#: rtol·dt·|x'|: on the DFKI pendulum recordings (0.06–1.5 % of a step from it) that is 1e-4–4e-4 rad, below their
#: encoder step of 2.9e-3 rad; their damaged file (7 %) and the one with a 22 ms gap (360 %) are refused.
JITTER_RTOL = 0.05
HOLDS = ("linear", "zoh")


def check_resample_step(dt: object) -> None:
    """`data.resample` is a step in seconds > 0 (null: off); 0, a negative, NaN or inf is refused."""
    if isinstance(dt, bool) or not isinstance(dt, int | float) or not (math.isfinite(dt) and dt > 0):
        raise ConfigError(
            f"data.resample must be a step in seconds > 0 (or null: use each file's own grid); got {dt!r}."
        )


def resample(rec: Trajectories, dt: float, hold: str = "linear") -> Trajectories:
    """`rec` on the uniform grid t0, t0 + dt, ... up to its last time (`data.resample=<dt>`).

    Args:
        rec: [B, T, N, D] states (and controls) on any strictly increasing grid.
        dt: the new step in seconds.
        hold: `data.input_hold`, how inputs are read between samples: ``linear`` interpolation, or ``zoh`` (zero-order
            hold: the sample at or before each new time). States are always interpolated linearly.
    """
    check_resample_step(dt)
    if hold not in HOLDS:
        raise ConfigError(f"data.input_hold must be one of {list(HOLDS)}; got {hold!r}.")
    t = rec.t.double()
    span = float(t[-1] - t[0])
    n = int(math.floor(span / dt + 1e-9)) + 1
    if n < 2:
        raise ConfigError(
            f"{rec.meta.get('source', 'data')}: data.resample={dt:g} s leaves fewer than 2 samples in a recording "
            f"of {span:g} s; use a smaller step."
        )
    new_t = t[0] + dt * torch.arange(n, dtype=torch.float64)  # [T'] uniform
    tol = 1e-9 * dt  # a new time that equals a sample's up to rounding is that sample
    right = torch.searchsorted(t, new_t + tol, right=True).clamp(1, len(t) - 1)  # first sample after each time
    left = right - 1
    weight = ((new_t - t[left]) / (t[right] - t[left])).clamp(0.0, 1.0)  # [T']
    x = _linear(rec.x, left, right, weight)
    u = None
    if rec.u is not None:
        at_or_before = (torch.searchsorted(t, new_t + tol, right=True) - 1).clamp(0, len(t) - 1)
        u = _linear(rec.u, left, right, weight) if hold == "linear" else rec.u[:, at_or_before]
    meta = {**rec.meta, "dt": float(dt), "resampled_from": rec.meta.get("dt"), "input_hold": hold}
    return replace(rec, t=new_t.to(rec.t.dtype), x=x, u=u, meta=meta)


def _linear(a: torch.Tensor, left: torch.Tensor, right: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    # a: [B, T, N, K]; left, right: [T'] sample indices; weight: [T'] share of the right sample
    w = weight.to(a.dtype)[None, :, None, None]
    return a[:, left] * (1 - w) + a[:, right] * w


def stride(rec: Trajectories, k: int, hold: str = "linear") -> Trajectories:
    """Every `k`-th sample of `rec`, the first kept (`data.stride=<k>`); `meta['dt']` becomes k times the step.

    An input held zero-order (`hold="zoh"`, as a DAC holds it) is not picked but averaged over the k samples each
    kept one stands for: the plant felt every one of them, and the mean over [t_j, t_j+k) held for the coarse step
    applies the same impulse. Picking every k-th value of a closed-loop input that changes every sample would
    replay another input than the one applied (a 1 kHz positioning axis at data.stride=10: the right model left
    a held-out error 10⁴× its null level). An input held `linear` (band-limited, sampled finely) is picked."""
    if isinstance(k, bool) or not isinstance(k, int) or k < 1:
        raise ConfigError(f"data.stride must be a whole number >= 1 (keep every k-th sample); got {k!r}.")
    if k == 1:
        return rec
    if (rec.n_times - 1) // k < 1:
        raise ConfigError(
            f"{rec.meta.get('source', 'data')}: data.stride={k} leaves fewer than 2 of its {rec.n_times} samples; "
            "use a smaller stride."
        )
    t = rec.t[::k]
    dt = float(torch.median(t[1:] - t[:-1]))
    meta = {**rec.meta, "dt": dt, "stride": k * int(rec.meta.get("stride", 1))}
    fine = rec.u
    u = None if fine is None else fine[:, ::k]
    if fine is not None and u is not None and hold == "zoh":
        block = torch.arange(fine.shape[1]) // k  # the kept sample each fine sample belongs to
        total = torch.zeros_like(u).index_add_(1, block, fine)
        u = total / torch.bincount(block, minlength=u.shape[1]).to(u.dtype)[None, :, None, None]
        meta["input_averaged"] = k
    return replace(rec, t=t, x=rec.x[:, ::k], u=u, meta=meta)


def uniform_fit(t: torch.Tensor) -> tuple[torch.Tensor, float, int]:  # t: [T] strictly increasing times
    """The uniform grid a + b·k closest to `t` (least squares), the largest distance of a time from it as a share
    of its step b, and the index of that time."""
    t = t.double()
    k = torch.arange(len(t), dtype=torch.float64)
    k_mean, t_mean = k.mean(), t.mean()
    step = float(((k - k_mean) * (t - t_mean)).sum() / ((k - k_mean) ** 2).sum())
    grid = t_mean + step * (k - k_mean)
    off = (t - grid).abs() / step
    worst = int(off.argmax())
    return grid, float(off[worst]), worst


def uniform_or_refuse(rec: Trajectories, rtol: float = JITTER_RTOL) -> Trajectories:
    """`rec` with its times snapped onto the uniform grid closest to them (least squares), if none is further from
    it than `rtol` of a step (`JITTER_RTOL` says why 5 %); else one message suggesting `data.resample`.

    A recording whose clock runs steadily keeps its timing (the grid's step is the clock's mean step); the jitter
    found is kept in ``meta['jitter']``, and times move by at most `rtol` of a step.
    """
    grid, off, k = uniform_fit(rec.t)
    step = float(grid[1] - grid[0])
    if off > rtol:
        t = rec.t.double()
        steps = t[1:] - t[:-1]
        median = float(steps.median())
        origin = float(rec.meta.get("t0", [0.0])[0])
        row = int(rec.meta.get("first_row", 0)) + k + 1
        raise DataError(
            f"{rec.meta.get('source', 'data')}: the sampling is not uniform: row {row} (t = "
            f"{origin + float(t[k]):.6g} s) lies {100 * off:.3g} % of a step from the uniform grid of step {step:.6g} s "
            f"(steps range from {float(steps.min()):.6g} to {float(steps.max()):.6g} s, median {median:.6g} s; up to "
            f"{100 * rtol:g} % is accepted). Interpolate onto a uniform grid with data.resample=<dt>, e.g. "
            f"data.resample={_round_step(median):g} (the median step)."
        )
    return replace(rec, t=grid.to(rec.t.dtype), meta={**rec.meta, "dt": step, "jitter": off})


def _round_step(step: float) -> float:
    """A round step near `step` to suggest (0.002 for 0.0020003)."""
    return float(f"{step:.2g}")
