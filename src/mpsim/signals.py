"""Input signals on a sample grid and how they are held between samples (`linear` or `zoh`), shared by the
driven white-box model (`mpsim.models.driving`) and the driven twin (`mpsim.systems.inputs`).

- ``linear``: interpolated linearly between u_k at t_k and u_{k+1} at t_{k+1} (a continuous signal);
- ``zoh`` (zero-order hold, as a DAC drives a motor): u_k on [t_k, t_{k+1}); the signal jumps at every sample.

Data say which in their metadata, ``meta["input_hold"]`` (`HOLD_KEY`; `linear` when absent).
"""

from __future__ import annotations

import bisect
from collections.abc import Mapping
from typing import Any

import torch

from mpsim.errors import ConfigError

HOLDS = ("linear", "zoh")
#: the data's metadata key that says how inputs are held between samples
HOLD_KEY = "input_hold"


def input_hold(meta: Mapping[str, Any] | None) -> str:
    """How the data hold their inputs between samples: ``meta["input_hold"]``, ``linear`` when absent.

    Raises:
        ConfigError: another value.
    """
    hold = (meta or {}).get(HOLD_KEY) or "linear"
    if hold not in HOLDS:
        raise ConfigError(
            f"the data's input_hold={hold!r} is not a hold; use data.input_hold=linear (interpolate between "
            "samples) or data.input_hold=zoh (each sample held until the next)."
        )
    return str(hold)


def hold_at(
    t_grid: torch.Tensor,  # [T] sample times
    u: torch.Tensor,  # [B, T, N, C] samples
    t: torch.Tensor,  # [] query time
    hold: str,
) -> torch.Tensor:
    """[B, N, C] the input at time `t`: the sample at or before `t` (zoh), or interpolated linearly between the
    samples around it (linear; constant beyond the grid). No host synchronisation (indices stay tensors)."""
    tq = t.reshape(1).to(t_grid)
    last = t_grid.numel() - 1
    k = (torch.searchsorted(t_grid, tq, right=True) - 1).clamp(0, last)  # [1] sample at or before t
    here = u.index_select(1, k).squeeze(1)
    if hold == "zoh" or last == 0:
        return here
    k = k.clamp(max=last - 1)
    lo, hi = t_grid.index_select(0, k), t_grid.index_select(0, k + 1)
    w = ((tq - lo) / (hi - lo)).clamp(0.0, 1.0).to(u)  # [1]
    a, b = u.index_select(1, k).squeeze(1), u.index_select(1, k + 1).squeeze(1)
    return a + w * (b - a)


class GridInput:
    """A rollout's input signal: samples `u` on the grid `t_grid`, held by `hold`; `held` = k fixes sample k (an
    interval-by-interval solve of zero-order-hold data sets it, see `mpsim.models.controls.integrate_held`)."""

    def __init__(
        self,
        t_grid: torch.Tensor,  # [T] sample times
        u: torch.Tensor,  # [B, T, N, C] samples (raw units)
        hold: str,
    ) -> None:
        self.t_grid, self.u, self.hold = t_grid, u, hold
        self.held: int | None = None
        # on the CPU the sample is found in a list of the grid's times (a solver evaluates the field about 7 times per
        # sample: a tensor search cost 20 µs of the field's 130); on a GPU `hold_at` keeps the host out of it
        self._times = t_grid.tolist() if t_grid.device.type == "cpu" and t_grid.numel() > 1 else None

    def __call__(self, t: torch.Tensor) -> torch.Tensor:  # t: [] time
        """[B, N, C] the input at time `t`."""
        if self.held is not None:
            return self.u[:, self.held]
        if self._times is None or t.numel() != 1:
            return hold_at(self.t_grid, self.u, t, self.hold)
        tq, last = float(t), len(self._times) - 1
        k = min(max(bisect.bisect_right(self._times, tq) - 1, 0), last)  # the sample at or before t
        if self.hold == "zoh":
            return self.u[:, k]
        k = min(k, last - 1)
        lo, hi = self._times[k], self._times[k + 1]
        w = min(max((tq - lo) / (hi - lo), 0.0), 1.0)
        a = self.u[:, k]
        return a + w * (self.u[:, k + 1] - a)
