"""Adaptive Dormand–Prince 5(4) with torchdiffeq's step control, written for small tensors.

MP-NODE's fields are small (a quadrotor batch is [128, 3, 26]), so a solve costs what its Python and tensor
bookkeeping costs, not what its arithmetic does: torchdiffeq's `dopri5` keeps the stages in one [..., 7] tensor
filled through an autograd Function, redoes its input checks and event-time setup at every call (a controlled
rollout calls it once per sample interval) and builds an autograd graph for every step-size computation.
Here the stages are a list, times and step sizes Python floats, and every stage combination and the dense
output one chain of fused adds (`y0 + dt Σ_j w_j k_j`, the interpolant's weights w_j computed in Python).

Same method, same steps: Hairer's initial step (Solving ODEs I, II.4), the 5th-order solution with the embedded
4th-order error estimate in the RMS norm of `err / (atol + rtol · max(|y0|, |y1|))`, accepted when ≤ 1, the next
step `dt · min(10, max(0.9 · ratio^(−1/5), 0.2))` (at least `dt` after a ratio below 1), the last stage of an
accepted step reused as the first of the next (FSAL), outputs by torchdiffeq's 4th-order interpolant through the
step's midpoint, and stages at the step's end evaluated just before it (so a field that reads a zero-order-hold
control at `t` sees the sample the step started in). In float64 it evaluates the field as often as torchdiffeq,
at the same times to 1e-10 (the error ratio is summed in another order), and its outputs agree to 1e-11
(tests/solvers/test_dopri5.py); in float32 they agree to rounding.

`restart=True` serves a field that jumps at every output time (an input held by a zero-order hold between
samples): no step straddles an output time — a step that would is cut to end on it — and at each output time the
field is evaluated afresh (the next sample) instead of reusing the last stage, while the step size carries on (no
new initial-step search). The same result as one solve per output interval, at about 7 field evaluations per
interval when the interval is shorter than the step the tolerance allows.

One difference, in the gradient: the step sizes are not differentiated. torchdiffeq backpropagates through its
first step size (a function of y0 and of the field), adding the derivative of the discretisation to every
solve's gradient; here step sizes are constants, as in a continuous adjoint (MPNODE.jl's default sensitivity)
and in torchdiffeq itself once a first step is given.
"""

from __future__ import annotations

import math

import torch
from torch import nn


class StepFailure(ArithmeticError):
    """The solve cannot go on: a non-finite state, an underflowed step, or too many steps for one output."""


# the Dormand–Prince tableau: stage times C, stage weights A[i] (row i builds stage i's input), the 5th-order
# solution B (= A[6], so stage 6 is evaluated at the step's end: FSAL), the error weights (5th − 4th order) and
# the weights of the solution at the step's midpoint, for the dense output (Shampine 1986)
C = (0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0, 1.0)
A = (
    (),
    (1 / 5,),
    (3 / 40, 9 / 40),
    (44 / 45, -56 / 15, 32 / 9),
    (19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729),
    (9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656),
    (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84),
)
B = (*A[6], 0.0)
ERROR = (
    35 / 384 - 1951 / 21600,
    0.0,
    500 / 1113 - 22642 / 50085,
    125 / 192 - 451 / 720,
    -2187 / 6784 + 12231 / 42400,
    11 / 84 - 649 / 6300,
    -1 / 60,
)
MID = (
    6025192743 / 30085553152 / 2,
    0.0,
    51252292925 / 65400821598 / 2,
    -2691868925 / 45128329728 / 2,
    187940372067 / 1594534317056 / 2,
    -1776094331 / 19743644256 / 2,
    11237099 / 235043384 / 2,
)
ORDER = 5
SAFETY, GROW, SHRINK = 0.9, 10.0, 0.2


def dopri5(
    func: nn.Module,  # vector field: forward(t [], y [B, ...]) -> [B, ...]
    y0: torch.Tensor,  # [B, ...] initial state
    t: torch.Tensor,  # [T] output times, strictly increasing or decreasing, t[0] the start
    rtol: float,
    atol: float,
    max_num_steps: int = 10_000,
    restart: bool = False,
) -> torch.Tensor:
    """[T, B, ...] the solution at each time in `t` (time first, as torchdiffeq's `odeint`).

    `restart`: the field jumps at every output time (see the module docstring): step to each one and restart there.

    Raises:
        StepFailure: the state became NaN/inf, the step size underflowed, or an output interval took more than
            `max_num_steps` steps.
    """
    times = [float(s) for s in t.tolist()]
    if len(times) > 1 and times[1] < times[0]:  # backwards in time: y(−s) solves dy/ds = −f(−s, y)
        return dopri5(_Reversed(func), y0, -t, rtol, atol, max_num_steps, restart)
    if any(b <= a for a, b in zip(times, times[1:], strict=False)):
        raise ValueError("dopri5: output times must be strictly increasing or strictly decreasing.")
    dtype = y0.dtype

    def at(s: float, just_before: bool = False) -> torch.Tensor:  # [] the time a stage sees, in the state's dtype
        ts = torch.tensor(s, dtype=dtype, device=y0.device)
        return torch.nextafter(ts, ts - 1) if just_before else ts

    t0, y, f = times[0], y0, func(at(times[0]), y0)
    dt = _initial_step(func, t0, y0, f, rtol, atol, at)
    out = [y0]
    step: tuple[float, float, torch.Tensor, list[torch.Tensor]] | None = None  # last accepted: t0, t1, y0, stages
    for t_out in times[1:]:
        n_steps = 0
        if restart and step is not None:  # on the last output time: the field has jumped, evaluate it afresh
            f, step = func(at(t0), y), None
        while step is None or t_out > step[1]:
            if n_steps >= max_num_steps:
                raise StepFailure(f"max_num_steps exceeded ({n_steps} steps for one output interval) at t={t0:.4g}")
            n_steps += 1
            if not math.isfinite(dt):
                raise StepFailure(f"non-finite values in the state or its derivative at t={t0:.4g}")
            t1 = t0 + dt
            if restart and t1 >= t_out:  # end exactly on the output time, never beyond it
                dt, t1 = t_out - t0, t_out
            if not t1 > t0:
                raise StepFailure(f"underflow in dt ({dt:.3g}) at t={t0:.4g}")
            ks = [f]
            for i in range(1, 7):
                y_i = _combine(y, ks, A[i], dt)
                ks.append(func(at(t1, True) if C[i] == 1.0 else at(t0 + C[i] * dt), y_i))
            y1 = y_i  # the 5th-order solution is stage 6's input
            with torch.no_grad():
                error = _combine(None, ks, ERROR, dt)
                ratio = _rms(error / (atol + rtol * torch.maximum(y.abs(), y1.abs())))
            if not math.isfinite(ratio):
                raise StepFailure(f"non-finite values in the state or its error estimate at t={t0:.4g}")
            if ratio <= 1:  # accepted
                step = (t0, t1, y, ks)
                t0, y, f = t1, y1, ks[6]
            if ratio == 0:
                dt = dt * GROW
            else:  # never shorter after a ratio below 1, never more than 5× shorter after a rejection
                dt = dt * min(GROW, max(SAFETY * ratio ** (-1 / ORDER), 1.0 if ratio < 1 else SHRINK))
        s0, s1, y_s, ks_s = step
        if restart:  # the last step ended on t_out
            out.append(y)
            continue
        out.append(_combine(y_s, ks_s, _dense_weights((t_out - s0) / (s1 - s0)), s1 - s0))
    return torch.stack(out)


class _Reversed(nn.Module):
    """The field of y(−s): dy/ds = −f(−s, y)."""

    def __init__(self, func: nn.Module) -> None:
        super().__init__()
        self.func = func

    def forward(self, s: torch.Tensor, y: torch.Tensor) -> torch.Tensor:  # s: [], y: [B, ...]
        return -self.func(-s, y)


def _initial_step(func, t0: float, y0: torch.Tensor, f0: torch.Tensor, rtol: float, atol: float, at) -> float:
    """Hairer, Nørsett & Wanner's starting step (one extra evaluation, not differentiated), as torchdiffeq's."""
    with torch.no_grad():
        scale = atol + y0.abs() * rtol
        d0, d1 = _rms(y0 / scale), _rms(f0 / scale)
        if not (math.isfinite(d0) and math.isfinite(d1)):  # an input of 1e30 makes f0 overflow: no step can start
            raise StepFailure(f"non-finite values in the state or its derivative at the start (t={t0:.4g})")
        h0 = 1e-6 if d0 < 1e-5 or d1 < 1e-5 else 0.01 * d0 / d1
        if not h0 > 0:
            raise StepFailure(f"underflow in the first step (derivative {d1:.3g} times the state's scale, t={t0:.4g})")
        f1 = func(at(t0 + h0), y0 + h0 * f0)
        d2 = _rms((f1 - f0) / scale) / h0
        if d1 <= 1e-15 and d2 <= 1e-15:
            h1 = max(1e-6, h0 * 1e-3)
        else:
            h1 = (0.01 / max(d1, d2)) ** (1 / ORDER)
        return min(100 * h0, h1)


def _combine(
    y: torch.Tensor | None,  # [B, ...] the step's start (None: the sum alone)
    ks: list[torch.Tensor],  # stages, each [B, ...]
    weights: tuple[float, ...] | list[float],
    dt: float,
) -> torch.Tensor:
    """[B, ...] y + dt Σ_j weights[j] ks[j] over the stages given (zero weights skipped)."""
    out = None
    for k, w in zip(ks, weights, strict=False):
        if w == 0.0:
            continue
        if out is None:
            out = k * (w * dt) if y is None else torch.add(y, k, alpha=w * dt)
        else:
            out.add_(k, alpha=w * dt)
    if out is None:
        return torch.zeros_like(ks[0]) if y is None else y.clone()
    return out


def _dense_weights(x: float) -> list[float]:
    """Weights w_j with y(t0 + x dt) ≈ y0 + dt Σ_j w_j k_j: torchdiffeq's quartic through y0, the midpoint and
    y1 with slopes k_0 and k_6 at the ends, its y0 terms cancelled (they sum to one) and collected per stage."""
    x2, x3, x4 = x * x, x**3, x**4
    weights = []
    for j in range(7):
        first, last, b, m = float(j == 0), float(j == 6), B[j], MID[j]
        weights.append(
            x * first
            + x2 * (last - 4 * first - 5 * b + 16 * m)
            + x3 * (5 * first - 3 * last + 14 * b - 32 * m)
            + x4 * (2 * last - 2 * first - 8 * b + 16 * m)
        )
    return weights


def _rms(x: torch.Tensor) -> float:
    return float(x.pow(2).mean().sqrt())
