"""How finely the data resolve each state variable: measurement noise and quantisation.

`noise_level` bounds the measurement-noise level from high-order time differences (used for the null data of
the residual loop); `resolution` is the smallest difference a variable's records can tell apart — the larger
of that noise level and the recording's quantisation step — which sets the smoothing scale of dry friction.
"""

from __future__ import annotations

import math

import torch

#: a resolution is never taken below this share of the variable's spread (clean, unquantised data)
MIN_RESOLUTION = 1e-3
#: nor above this share: beyond it tanh(v/ε) is nearly linear and dry friction would be viscous damping
MAX_RESOLUTION = 0.05


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


def resolution(x: torch.Tensor) -> torch.Tensor:  # x: [B, T, N, D]
    """[D] per variable: max(noise level, quantisation step), clamped to [MIN_RESOLUTION, MAX_RESOLUTION] × its
    standard deviation — velocities below it cannot be told from zero, so sign(v) is smoothed over it."""
    flat = x.double().reshape(-1, x.shape[-1])
    spread = torch.nan_to_num(flat[torch.isfinite(flat).all(dim=1)].std(0), nan=1.0).clamp_min(1e-12)
    raw = torch.maximum(noise_level(x), quantisation_step(x))
    return torch.minimum(torch.maximum(raw, MIN_RESOLUTION * spread), MAX_RESOLUTION * spread)
