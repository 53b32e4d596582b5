"""The trivial N-body baseline: every particle keeps its initial velocity (ballistic motion, no forces).

    q(t) = wrap(q0 + v0 (t - t0)),   v(t) = v0

It needs no training. `mpsim train model=constant_velocity trainer.max_epochs=0 system=nbody100` evaluates it
on the test split (epoch 0 is the evaluation of the model as built), with the same metrics as the learned
models, including the paper's energy error. Spec §6: its 20-step RMSE at N = 100 is about 0.156 — a learned
simulator's number only means something next to this one.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from mpsim.errors import ConfigError
from mpsim.models.base import Model
from mpsim.models.nbody_base import EnergyLog, check_particle_data, particle_features
from mpsim.periodic import wrap_positions

if TYPE_CHECKING:
    from collections.abc import Callable

    from mpsim.data.trajectories import Inputs, Trajectories


class ConstantVelocity(Model):
    """Ballistic particles: positions advance with the initial velocity, velocities stay constant.

    Args:
        state_dim: 4 (x, y, vx, vy); other data is refused by `check_compatible`.
        control_dim: 0.
        energy_horizons: steps at which the paper's energy error is reported.
        energy_flag: see `nbody_base.EnergyLog`.
        solver: unused; accepted from the command layer.
    """

    def __init__(
        self,
        state_dim: int = 4,
        control_dim: int = 0,
        energy_horizons: Sequence[int] = (20, 200),
        energy_flag: float = 0.1,
        solver: Any = None,
    ) -> None:
        super().__init__(state_dim, control_dim)
        # A frozen unit gain on the drift (q0 + gain · v0 t). It exists only so that the generic Trainer can
        # build its optimiser (Adam refuses an empty parameter list); it never changes.
        self.gain = nn.Parameter(torch.ones(()), requires_grad=False)
        self.energy = EnergyLog(energy_horizons, energy_flag)

    def check_compatible(
        self, state_dim: int, control_dim: int, n_nodes: int, trained_nodes: int | None = None
    ) -> None:
        check_particle_data("ConstantVelocity", state_dim, control_dim)

    def rollout(
        self,
        x0: torch.Tensor,  # [B, N, 4] initial states
        t: torch.Tensor,  # [T] times
        inputs: Inputs,  # node features [B, N, 2] or [N, 2] (mass, charge, for the energy), meta: box_size, params
    ) -> torch.Tensor:
        """[B, T, N, 4] ballistic trajectories (positions wrapped into the box when the data has one)."""
        meta = inputs.meta
        elapsed = (t - t[0]).to(x0)[None, :, None, None]  # [1, T, 1, 1]
        pos = x0[:, None, :, :2] + self.gain * x0[:, None, :, 2:] * elapsed  # [B, T, N, 2]
        box = (meta or {}).get("box_size")
        if box is not None:
            pos = wrap_positions(pos, float(box))
        pred = torch.cat([pos, x0[:, None, :, 2:].expand_as(pos)], dim=-1)
        if not torch.is_grad_enabled():
            b, n, _ = x0.shape
            self.energy.record(pred, particle_features(inputs.node_features, b, n, x0), meta)
        return pred

    def training_loss(
        self,
        batch: Trajectories,
        t: torch.Tensor,
        loss_fn: Callable[..., torch.Tensor] | None = None,
        delta: float = 1.0,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        raise ConfigError(
            "model=constant_velocity has nothing to train: run it with trainer.max_epochs=0 (the epoch-0 "
            "evaluation and the final test metrics are its results)."
        )

    def describe(self) -> dict[str, Any]:
        return {"model": type(self).__name__, "n_params": 0}

    def report(self) -> dict[str, Any]:
        return {"nbody": {"graph": "none", **self.energy.summary()}}

    def report_lines(self) -> list[tuple[str, str]]:
        return self.energy.lines()
