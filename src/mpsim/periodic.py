"""Periodic geometry: the minimum image of a separation, positions wrapped into the box, and state differences
with periodic features (positions in a periodic box, phases on the circle).

The one place where a period wraps a coordinate: the particle graphs, the N-body simulator, the models' losses
and the metrics all use these, so an edge vector, a pair force and an error agree on which copy is nearest.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch


def minimum_image(
    d: torch.Tensor,  # [..., D] separation vectors
    box_size: float | torch.Tensor,  # the period: a number, or a tensor broadcasting against d (e.g. [D])
) -> torch.Tensor:
    """[..., D] `d` with each component wrapped into [-L/2, L/2] (the nearest periodic copy).

    Uses round-half-to-even, which is odd-symmetric (mi(-d) = -mi(d)), so the vector of an edge is exactly
    minus that of the reversed edge, even at the measure-zero tie |d| = L/2, and pair forces stay exactly
    antisymmetric (momentum is conserved to round-off).
    """
    return d - box_size * torch.round(d / box_size)


def wrap_positions(
    pos: torch.Tensor,  # [..., D] positions
    box_size: float,
) -> torch.Tensor:
    """[..., D] positions mapped into the half-open box [-L/2, L/2)."""
    return pos - box_size * torch.floor(pos / box_size + 0.5)


def state_difference(
    pred: torch.Tensor,  # [..., D] predicted states
    target: torch.Tensor,  # [..., D] true states
    periods: Sequence[float | None] | None = None,  # per feature: period of a periodic coordinate, or None
) -> torch.Tensor:
    """[..., D] pred − target, the periodic features taken by their minimum image (phases on the circle,
    positions in a periodic box), so that wrapping never counts as an error."""
    diff = pred - target
    if not periods or all(p is None for p in periods):
        return diff
    period = torch.tensor([p if p else math.inf for p in periods], dtype=diff.dtype, device=diff.device)
    periodic = torch.isfinite(period)
    wrapped = minimum_image(diff, torch.where(periodic, period, torch.ones_like(period)))
    return torch.where(periodic, wrapped, diff)
