"""Per-node control inputs for learned vector fields: z-scoring and the zero-order hold.

Zero-order hold. Sample k's control acts on [t_k, t_{k+1}). One adaptive solve over the whole grid would step
across the sample times, where the held input jumps: a step that straddles t_k mixes u_{k-1} and u_k, and
the state reported at t_k already feels u_k (dense output of that step). With controls, models therefore
solve one interval at a time with the input fixed to its sample (`integrate_held`), as MPNODE.jl does.

Recorded controls are rarely O(1) numbers: the quadrotor's rotor thrusts sit at 3.3 ± 0.2 N, so a network fed
raw thrusts sees an almost constant input whose informative part is a twentieth of a state feature's spread.
Models therefore z-score controls per channel with statistics of their training data, kept as buffers (they
travel with the checkpoint, so a finetuned or zero-shot model reads controls in the units it learned).

No hook of the training loop sees the whole training split, so the statistics are fitted once, from the first
training batch (thousands of samples per channel: 32 trajectories × 51 times × N nodes), and then frozen.
They follow the state statistics: a finetune keeps the checkpoint's, and when the command layer refits the
state normalisation (`set_normalisation`: a fresh model, or `mode.refit_normalisation=true`) the models call
`refit`, so the next training batch refits the controls too (the old values stay in use until then). Before
any fit (an untrained model's epoch-0 evaluation) controls pass through unscaled. A model without controls
registers no buffers, so checkpoints of control-free models are unchanged.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from mpsim.models.base import Model


class ControlNormalisation(nn.Module):
    """Per-channel z-score of controls with statistics fitted once from training data.

    Args:
        control_dim: C, controls per node (0: the module is a no-op without buffers).
        min_std: a channel whose spread is below this is only centred (a constant input).
    """

    # buffers, registered when control_dim > 0 (nn.Module.__getattr__ would type them as Tensor | Module)
    mean: torch.Tensor
    std: torch.Tensor
    fitted: torch.Tensor

    def __init__(self, control_dim: int, min_std: float = 1e-6) -> None:
        super().__init__()
        self.control_dim, self.min_std = int(control_dim), float(min_std)
        if self.control_dim > 0:
            self.register_buffer("mean", torch.zeros(self.control_dim))
            self.register_buffer("std", torch.ones(self.control_dim))
            self.register_buffer("fitted", torch.zeros((), dtype=torch.bool))

    @torch.no_grad()
    def fit(self, u: torch.Tensor) -> None:  # u: [..., C] raw controls
        """Set the statistics from `u` (pooled over every axis but the channel) and mark them fitted."""
        flat = u.reshape(-1, self.control_dim).to(self.mean.dtype)
        std = flat.std(0) if flat.shape[0] > 1 else torch.ones_like(self.std)
        self.mean.copy_(flat.mean(0))
        self.std.copy_(torch.where(std > self.min_std, std, torch.ones_like(std)))
        self.fitted.fill_(True)

    def refit(self) -> None:
        """Mark the statistics stale: the next `fit_once` fits them again (they stay in use until then)."""
        if self.control_dim > 0:
            self.fitted.fill_(False)

    def fit_once(self, u: torch.Tensor | None) -> None:  # u: [B, T, N, C] raw controls of a training batch
        """Fit from `u` unless already fitted (first training batch, or loaded from a checkpoint)."""
        if self.control_dim > 0 and u is not None and not bool(self.fitted):
            self.fit(u)

    def forward(self, u: torch.Tensor | None) -> torch.Tensor | None:  # u: [..., C] raw controls
        """[..., C] z-scored controls (None passes through)."""
        if u is None or self.control_dim == 0:
            return u
        return (u - self.mean.to(u)) / self.std.to(u)


def zero_order_hold(
    t_grid: torch.Tensor,  # [T] sample times of u
    u: torch.Tensor | None,  # [B, T, N, C] controls
    t: torch.Tensor,  # [] query time
    held: int | None = None,
) -> torch.Tensor | None:
    """[B, N, C] the control sample at or before `t` (held until the next sample), or sample `held` when an
    interval-by-interval solve fixes it; None without controls."""
    if u is None:
        return None
    if held is not None:
        return u[:, held]
    k = torch.searchsorted(t_grid, t.reshape(1).to(t_grid), right=True).clamp(1, t_grid.numel()) - 1
    return u[:, int(k)]


class HeldField(nn.Module):
    """A vector field of one rollout that reads controls `u` (or None) through a zero-order hold, with `held`
    the sample an interval-by-interval solve fixes (None: the sample at or before t)."""

    u: torch.Tensor | None
    held: int | None


def integrate_held(
    integrate: Callable[[nn.Module, torch.Tensor, torch.Tensor], torch.Tensor],
    field: HeldField,
    y0: torch.Tensor,  # [B, ...] initial state
    t: torch.Tensor,  # [T] output times (= the control sample times)
) -> torch.Tensor:
    """[B, T, ...] the field integrated one sample interval at a time with `field.held` = the interval's
    control sample (a single solve over the grid when `field.u` is None: nothing jumps).

    Args:
        integrate: (field, y0 [B, ...], t [2 or T]) → [B, len(t), ...], e.g. the model's `integrate`.
        field: a vector field with attributes `u` (controls or None) and `held` (sample index or None).
    """
    if getattr(field, "u", None) is None:
        return integrate(field, y0, t)
    states = [y0]
    try:
        for k in range(t.numel() - 1):  # sequential in time only; every trajectory and node at once
            field.held = k
            states.append(integrate(field, states[-1], t[k : k + 2])[:, 1])
    finally:
        field.held = None
    return torch.stack(states, dim=1)


class ControlledModel(Model):
    """A model that reads per-node controls through a `ControlNormalisation` (`self.controls`): its control
    statistics follow the state statistics and are fitted on the first training batch."""

    controls: ControlNormalisation

    def set_normalisation(
        self,
        mean: torch.Tensor,  # [D] per-feature mean of the training states
        std: torch.Tensor,  # [D] per-feature standard deviation
    ) -> None:
        """Set the state statistics; the control statistics follow (refit on the next training batch)."""
        super().set_normalisation(mean, std)
        self.controls.refit()

    def training_loss(self, batch, t, loss_fn, delta=1.0):
        """Single shooting (the base class's), after fitting the control scale on the first training batch."""
        self.controls.fit_once(batch.u)
        return super().training_loss(batch, t, loss_fn, delta)
