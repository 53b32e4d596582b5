"""Optional model capabilities that only the residual loop (`mpsim.diagnose`) reads.

`Model` holds what every model needs (normalisation, compatibility checks, rollout, training loss). What the
residual loop can use beyond that is declared here as runtime-checkable protocols: a model has a capability
when it defines the protocol's members, and the loop checks each with `isinstance`. A model without one is
treated as having nothing to declare (no represented kinds, no latent state, no interpretable parameters) and
is stepped along the data by one rollout per step (`one_step_by_rollouts`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import torch

from mpsim.data.trajectories import Inputs

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
        edge_index: torch.Tensor,  # [2, E] or [B, 2, E]
        *,
        u: torch.Tensor | None = None,  # [B, T, N, C] controls
        node_features: torch.Tensor | None = None,  # [N, F] or [B, N, F]
        meta: dict[str, Any] | None = None,  # the data's metadata
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
        """[M, N, D, P] derivatives of the model's vector field with respect to its P parameters, or None."""
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
    edge_index: torch.Tensor,  # [2, E] or [B, 2, E]
    *,
    u: torch.Tensor | None = None,  # [B, T, N, C] controls
    node_features: torch.Tensor | None = None,  # [N, F] or [B, N, F]
    meta: dict[str, Any] | None = None,  # the data's metadata
) -> torch.Tensor:
    """[B, T−1, N, D] `model`'s prediction of each x_{k+1} from the observed x_k: its own `one_step` when it is a
    `OneStepPredictor`, else `one_step_by_rollouts`."""
    inputs: dict[str, Any] = {"u": u, "node_features": node_features, "meta": meta}
    if isinstance(model, OneStepPredictor):
        return model.one_step(x, t, edge_index, **inputs)
    return one_step_by_rollouts(model, x, t, edge_index, **inputs)


def one_step_by_rollouts(
    model: Model,
    x: torch.Tensor,  # [B, T, N, D] observed states (raw units)
    t: torch.Tensor,  # [T] times
    edge_index: torch.Tensor,  # [2, E] or [B, 2, E]
    *,
    u: torch.Tensor | None = None,  # [B, T, N, C] controls
    node_features: torch.Tensor | None = None,  # [N, F] or [B, N, F]
    meta: dict[str, Any] | None = None,  # the data's metadata
) -> torch.Tensor:
    """[B, T−1, N, D] each x_{k+1} predicted from the observed x_k by a one-step rollout at its absolute time."""
    steps = []
    for k in range(x.shape[1] - 1):  # sequential in time only; each step batches every trajectory
        uk = None if u is None else u[:, k : k + 2]
        inputs = Inputs(edge_index, uk, node_features, {} if meta is None else meta)
        steps.append(model.rollout(x[:, k], t[k : k + 2], inputs)[:, 1])
    return torch.stack(steps, dim=1)
