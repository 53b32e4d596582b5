"""How finely measured data resolve each variable: measurement noise and quantisation.

`noise_level` bounds the measurement-noise level from high-order time differences; `quantisation_step` is the
smallest gap between recorded values (an encoder's count, a DAC's step); `noise_summary` states both per named
state and input of a `Trajectories` (what the report says of the data). The residual loop's null data and dry
friction's smoothing scale (`mpsim.diagnose.noise`) are built on them.
"""

from __future__ import annotations

import math
from typing import Any

import torch

from mpsim.data.trajectories import Trajectories

#: gaps between distinct values may differ from whole multiples of the smallest one by this share of it, and the
#: values still count as sitting on a grid
GRID_RTOL = 0.05
#: a grid's smallest gap may span this many of its steps (levels never visited)
MAX_SKIP = 4


def noise_level(x: torch.Tensor, residual_steps: torch.Tensor | None = None) -> torch.Tensor:
    """[D] measurement-noise standard deviation, the smallest of several upper bounds.

    Args:
        x: [B, T, N, D] observed states. For white noise of std σ the k-th difference along time has variance
            C(2k, k)·σ²; the smooth signal adds O((ωΔ)^k), so each even order k ≤ 6 bounds σ from above.
        residual_steps: [B, T−1, N, D] one-step residuals times the step, x_{k+1} − Φ(x_k). Noise enters them as
            ε_{k+1} − Φ'ε_k ≈ ε_{k+1} − ε_k, so their k-th differences have variance C(2k+2, k+1)·σ², while the
            model's error is smooth in time and far smaller than the signal: a much tighter bound.

    On clean data the result is a small upper bound, which only makes the null check more conservative.
    """
    bounds = [_difference_bound(x.double(), shift=0)]
    if residual_steps is not None:
        bounds.append(_difference_bound(residual_steps.double(), shift=1))
    best = torch.stack(bounds).min(dim=0).values
    return torch.where(torch.isfinite(best), best, torch.zeros_like(best))


def _difference_bound(x: torch.Tensor, shift: int) -> torch.Tensor:  # x: [B, T, N, D]
    finite = torch.isfinite(x).flatten(1).all(dim=1)
    x = x[finite]
    best = torch.full((x.shape[-1],), math.inf, dtype=torch.float64)
    diff = x
    for k in range(1, 7):
        diff = diff[:, 1:] - diff[:, :-1]
        if diff.shape[1] < 2 or diff.shape[0] == 0:
            break
        if k % 2 == 0:
            est = diff.reshape(-1, x.shape[-1]).std(0) / math.sqrt(math.comb(2 * (k + shift), k + shift))
            best = torch.minimum(best, est)
    return best


def quantisation_step(x: torch.Tensor) -> torch.Tensor:  # x: [B, T, N, D]
    """[D] the smallest positive gap between distinct recorded values of each variable (data logged on a grid,
    e.g. an encoder's counts, have it at the grid step; for continuous values it is negligible)."""
    flat = x.double().reshape(-1, x.shape[-1])
    out = torch.zeros(flat.shape[-1], dtype=torch.float64)
    for d in range(flat.shape[-1]):  # a loop over the few state variables
        v = flat[:, d][torch.isfinite(flat[:, d])].unique()  # sorted
        gaps = v[1:] - v[:-1]
        if gaps.numel():
            out[d] = gaps.min()
    return out


def grid_quantum(x: torch.Tensor) -> float | None:  # x: [...] one variable's values
    """The step of the grid the distinct finite values of `x` sit on, or None when they sit on none.

    The step is the smallest gap divided by the smallest m in 1..`MAX_SKIP` for which every gap is a whole
    multiple of it (within `GRID_RTOL`): a recording that never visits alternate levels has a smallest gap of two
    steps. Continuous readings (as many distinct values as samples, or gaps that are no multiples) sit on none."""
    values = x.double().reshape(-1)
    values = values[torch.isfinite(values)].unique()
    if values.numel() < 3 or values.numel() >= x.numel():
        return None
    gaps = values[1:] - values[:-1]
    smallest = float(gaps.min())
    for m in range(1, MAX_SKIP + 1):
        ratio = gaps / (smallest / m)
        if bool(((ratio - ratio.round()).abs() <= GRID_RTOL).all()):
            return smallest / m
    return None


def noise_summary(data: Trajectories) -> dict[str, dict[str, Any]]:
    """Per state and input name: ``std`` (the measurement-noise level, `noise_level`) and ``quantum`` (the
    quantisation step, `grid_quantum`, or None when the values do not sit on a grid).

    Pooled over trajectories and nodes: segments of one recording, or recordings of one sensor, share them.
    """
    out: dict[str, dict[str, Any]] = {}
    for names, values in ((data.state_names, data.x), (data.control_names, data.u)):
        if values is None:
            continue
        stds = noise_level(values)
        for k, name in enumerate(names):  # a loop over the few variables
            out[name] = {"std": float(stds[k]), "quantum": grid_quantum(values[..., k])}
    return out
