"""How finely the data resolve each state variable: measurement noise and quantisation.

`noise_level` bounds the measurement-noise level from high-order time differences (used for the null data of
the residual loop); `resolution` is the smallest difference a variable's records can tell apart — the larger
of that noise level and the recording's quantisation step — which sets the smoothing scale of dry friction.
"""

from __future__ import annotations

import torch

from mpsim.data.noise import noise_level as noise_level
from mpsim.data.noise import quantisation_step as quantisation_step

#: a resolution is never taken below this share of the variable's spread (clean, unquantised data)
MIN_RESOLUTION = 1e-3
#: nor above this share: beyond it tanh(v/ε) is nearly linear and dry friction would be viscous damping
MAX_RESOLUTION = 0.05


def resolution(x: torch.Tensor) -> torch.Tensor:  # x: [B, T, N, D]
    """[D] per variable: max(noise level, quantisation step), clamped to [MIN_RESOLUTION, MAX_RESOLUTION] × its
    standard deviation — velocities below it cannot be told from zero, so sign(v) is smoothed over it."""
    flat = x.double().reshape(-1, x.shape[-1])
    spread = torch.nan_to_num(flat[torch.isfinite(flat).all(dim=1)].std(0), nan=1.0).clamp_min(1e-12)
    raw = torch.maximum(noise_level(x), quantisation_step(x))
    return torch.minimum(torch.maximum(raw, MIN_RESOLUTION * spread), MAX_RESOLUTION * spread)
