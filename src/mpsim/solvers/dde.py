"""Fixed-step RK4 for delay differential equations (method of steps with interpolated history).

Used when a system or model carries a `DelayedFeedback` effect: the right-hand side then reads the state
at t − τ, which an ODE solver cannot provide. The history before t0 is the constant initial state; between
stored steps it is interpolated linearly (second-order accurate, enough for τ ≥ a few steps).
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
    y0: torch.Tensor,  # [B, ...] initial state (also the constant history before t0)
    t: torch.Tensor,  # [T] uniform output times
    step: float,
    min_delay: float,
) -> torch.Tensor:
    """[B, T, ...] solution of dy/dt = func(t, y, history) sampled at `t`.

    Args:
        func: right-hand side; `history(s)` returns the state at an earlier time s.
        step: largest internal step (reduced to divide the output interval and to stay ≤ `min_delay`,
            so that every history query falls on already computed states).
        min_delay: the smallest delay in the right-hand side.
    """
    dt_out = float(t[1] - t[0]) if t.numel() > 1 else step
    if t.numel() > 1 and not torch.allclose(t[1:] - t[:-1], torch.full_like(t[1:], dt_out), rtol=1e-4, atol=1e-6):
        raise ConfigError("delay effects need a uniform time grid.")
    sub = delay_substeps(dt_out, step, min_delay)
    h = dt_out / sub
    t0 = float(t[0])
    states = [y0]  # states at t0 + k h

    def history(s: torch.Tensor) -> torch.Tensor:
        pos = (float(s) - t0) / h
        if pos <= 0:
            return y0
        k = min(int(math.floor(pos)), len(states) - 1)
        frac = pos - k
        if frac <= 1e-12 or k + 1 >= len(states):
            return states[k]
        return states[k] + frac * (states[k + 1] - states[k])

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
