"""Optional model capabilities that only the residual loop (`mpsim.diagnose`) reads.

`Model` holds what every model needs (normalisation, compatibility checks, rollout, training loss). What the
residual loop can use beyond that is declared here as runtime-checkable protocols: a model has a capability
when it defines the protocol's members, and the loop checks each with `isinstance`. A model without one is
treated as having nothing to declare (no represented kinds, no latent state, no interpretable parameters) and
is stepped along the data by one rollout per step (`one_step_by_rollouts`).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import torch

from mpsim.data.trajectories import Inputs
from mpsim.effects import max_delay

if TYPE_CHECKING:
    from mpsim.models.base import Model


@runtime_checkable
class ExpressesEffects(Protocol):
    """A model that can express some effect kinds by itself: the residual loop refits their directions as
    nuisance instead of naming them, and leaves out the kinds it cannot tell apart from the model's error."""

    #: effect kinds (class names in `mpsim.effects`) the model can express by itself
    represents: tuple[str, ...]
    #: effect kinds that cannot be told apart from this model's own error (left out of the library)
    indistinguishable: tuple[str, ...]
    #: degree of the polynomials of a node's own state the model can express (0: none); refit as nuisance
    represents_polynomials: int


@runtime_checkable
class LatentState(Protocol):
    """A model with a latent state (MP-NODE messages) that its one-step predictions carry along the data."""

    #: the latent state restarts at zero every this many steps — set to the training window, over which it
    #: was trained (None: carry it throughout)
    latent_reset: int | None


@runtime_checkable
class OneStepPredictor(Protocol):
    """A model with its own one-step predictions along an observed trajectory (batched, or carrying a latent
    state); without it the residual loop uses `one_step_by_rollouts`."""

    def one_step(
        self,
        x: torch.Tensor,  # [B, T, N, D] observed states (raw units)
        t: torch.Tensor,  # [T] times
        inputs: Inputs,  # graph [2, E] or [B, 2, E], controls [B, T, N, C] on the grid t, node features, meta
    ) -> torch.Tensor: ...


@runtime_checkable
class Interpretable(Protocol):
    """A model with a few interpretable parameters (white-box models, discovered coefficients). The residual
    loop refits their directions alongside its candidates, so that a parameter that absorbed part of a missing
    effect is not mistaken for another effect, and applies the refit's correction."""

    def sensitivities(
        self,
        t: torch.Tensor,  # [M, 1] or [] times
        x: torch.Tensor,  # [M, N, D] states (raw units)
        edge_index: torch.Tensor,  # [2, E] graph
    ) -> torch.Tensor | None:
        """[M, N, D, P] derivatives of the model's vector field with respect to its P parameters, or None. A model
        whose field reads inputs also takes them, as the keyword `u` [M, N, C] (the inputs with those states)."""
        ...

    def sensitivity_names(self) -> list[str]:
        """Names of the P parameters of `sensitivities`."""
        ...

    def shift_parameters(self, shifts: dict[str, float]) -> None:
        """Add `shifts` to the named parameters (names not among them are ignored)."""
        ...


def one_step(
    model: Model,
    x: torch.Tensor,  # [B, T, N, D] observed states (raw units)
    t: torch.Tensor,  # [T] times
    inputs: Inputs,  # graph [2, E] or [B, 2, E], controls [B, T, N, C] on the grid t, node features, meta
) -> torch.Tensor:
    """[B, T−1, N, D] `model`'s prediction of each x_{k+1} from the observed x_k: its own `one_step` when it is a
    `OneStepPredictor`, else `one_step_by_rollouts`."""
    if isinstance(model, OneStepPredictor):
        return model.one_step(x, t, inputs)
    return one_step_by_rollouts(model, x, t, inputs)


def one_step_by_rollouts(
    model: Model,
    x: torch.Tensor,  # [B, T, N, D] observed states (raw units)
    t: torch.Tensor,  # [T] times
    inputs: Inputs,  # graph [2, E] or [B, 2, E], controls [B, T, N, C] on the grid t, node features, meta
) -> torch.Tensor:
    """[B, T−1, N, D] each x_{k+1} predicted from the observed x_k by a one-step rollout at its absolute time
    (the controls `inputs.u` cut to that step's two samples; the graph, node features and meta as they are; a
    delayed effect reads the observed states before x_k as its history, `Inputs.past`)."""
    u = inputs.u
    reach = max_delay(model.effects)
    p = min(math.ceil(reach / float(t[1] - t[0]) - 1e-9) + 1, t.numel()) if reach > 0 and t.numel() > 1 else 0
    steps = []
    for k in range(x.shape[1] - 1):  # sequential in time only; each step batches every trajectory
        past = x[:, (k - p + torch.arange(p)).clamp(min=0)] if p else None  # [B, P, N, D] the record before x_k
        step_inputs = replace(inputs, u=None if u is None else u[:, k : k + 2], past=past)
        steps.append(model.rollout(x[:, k], t[k : k + 2], step_inputs)[:, 1])
    return torch.stack(steps, dim=1)
