"""Fixed-step RK4 for delay differential equations (method of steps with interpolated history).

Used when a system or model carries a `DelayedFeedback` effect: the right-hand side then reads the state
at t − τ, which an ODE solver cannot provide. The history before t0 is the recorded past when one is given
(`past`: the samples before t0, e.g. the data before a window's start), else the constant initial state; before
the past's first sample it is held constant. Between stored states it is interpolated linearly (second-order
accurate), so τ need not be a multiple of any step, and a query time that carries a gradient (a fitted τ) passes
it on through the interpolation weight.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from mpsim.errors import ConfigError, DivergenceError


def delay_substeps(interval: float, step: float, min_delay: float) -> int:
    """RK4 steps per output interval in `rk4_delay`: no longer than `step` nor than the smallest delay."""
    h_max = min(step, min_delay) if min_delay > 0 else step
    return max(1, math.ceil(interval / h_max - 1e-9))


def rk4_delay(
    func: Callable[[torch.Tensor, torch.Tensor, Callable[[torch.Tensor], torch.Tensor]], torch.Tensor],
    y0: torch.Tensor,  # [B, ...] initial state (also the constant history before t0 without `past`)
    t: torch.Tensor,  # [T] uniform output times
    step: float,
    min_delay: float,
    past: torch.Tensor | None = None,  # [B, P, ...] states at t0 − P·Δ … t0 − Δ (Δ = the output interval)
) -> torch.Tensor:
    """[B, T, ...] solution of dy/dt = func(t, y, history) sampled at `t`.

    Args:
        func: right-hand side; `history(s)` returns the state at an earlier time s (a tensor; its gradient,
            e.g. with respect to a fitted delay, flows through the interpolation weight).
        step: largest internal step (reduced to divide the output interval and to stay ≤ `min_delay`,
            so that every history query falls on already computed states).
        min_delay: the smallest delay in the right-hand side.
        past: the recorded states before t0 on the output grid (None: the history before t0 is y0).
    """
    dt_out = float(t[1] - t[0]) if t.numel() > 1 else step
    if t.numel() > 1 and not torch.allclose(t[1:] - t[:-1], torch.full_like(t[1:], dt_out), rtol=1e-4, atol=1e-6):
        raise ConfigError("delay effects need a uniform time grid.")
    sub = delay_substeps(dt_out, step, min_delay)
    h = dt_out / sub
    t0 = float(t[0])
    # knots of the history at t0 + k h, k from −(P·sub) (the past, upsampled linearly: the same piecewise-linear
    # function) to the last computed step
    states = [y0] if past is None or past.shape[1] == 0 else list(_upsample(past, y0, sub).unbind(1))
    first = 1 - len(states)  # the index k of states[0]

    def history(s: torch.Tensor) -> torch.Tensor:
        pos = (torch.as_tensor(s, dtype=y0.dtype) - t0) / h - first  # place among the knots
        p = float(pos.detach())
        if p <= 0 or len(states) == 1:
            return states[0]  # held constant before the first knot
        k = min(int(math.floor(p)), len(states) - 2)  # past the last knot: extrapolated from the last two
        return states[k] + (pos - k) * (states[k + 1] - states[k])

    out = [y0]
    y = y0
    for i in range(1, t.numel()):  # integration is sequential in time
        for j in range(sub):
            tn = torch.tensor(t0 + ((i - 1) * sub + j) * h, dtype=y0.dtype)
            k1 = func(tn, y, history)
            k2 = func(tn + h / 2, y + h / 2 * k1, history)
            k3 = func(tn + h / 2, y + h / 2 * k2, history)
            k4 = func(tn + h, y + h * k3, history)
            y = y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            states.append(y)
        if not torch.isfinite(y).all():
            raise DivergenceError(f"delay integration became non-finite at t={float(t[i]):.4g}.")
        out.append(y)
    return torch.stack(out, dim=1)


def _upsample(
    past: torch.Tensor,  # [B, P, ...] samples at spacing Δ before y0
    y0: torch.Tensor,  # [B, ...] the state at t0
    sub: int,
) -> torch.Tensor:
    """[B, P·sub + 1, ...] the piecewise-linear interpolant of past and y0 at spacing Δ/sub (y0 last)."""
    pts = torch.cat([past.to(y0), y0[:, None]], dim=1)  # [B, P+1, ...]
    w = torch.arange(sub, dtype=y0.dtype, device=y0.device) / sub  # [sub]
    shape = (1, 1, sub) + (1,) * (y0.dim() - 1)
    lo, hi = pts[:, :-1, None], pts[:, 1:, None]  # [B, P, 1, ...]
    inner = (lo + w.reshape(shape) * (hi - lo)).flatten(1, 2)  # [B, P·sub, ...]
    return torch.cat([inner, y0[:, None]], dim=1)
