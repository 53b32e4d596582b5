"""`Model`: the interface every learned or white-box simulator implements.

A model maps initial node states to a predicted trajectory on a given graph: `rollout(x0, t, inputs)`, where
`inputs` (`mpsim.data.trajectories.Inputs`) holds the graph, controls, node features and metadata.
It holds the normalisation statistics of the data it was trained on (`state_mean`, `state_std`, buffers
saved with its weights) and takes and returns states in raw units, so a checkpoint can be used on new data
without any outside bookkeeping. Training losses are computed in normalised units (see `normalise`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING, Any, overload

import torch
from torch import nn

from mpsim.effects import Effect, min_delay
from mpsim.errors import IncompatibleError
from mpsim.metrics import select_features
from mpsim.solvers.dde import rk4_delay

if TYPE_CHECKING:
    from mpsim.data.trajectories import Inputs, Trajectories


class EffectList(nn.ModuleList):
    """`nn.ModuleList` of `Effect`s, typed as such (a plain ModuleList's items read as `Module`)."""

    def __iter__(self) -> Iterator[Effect]:
        return super().__iter__()  # type: ignore[return-value]  # only Effects are ever appended

    @overload
    def __getitem__(self, idx: slice) -> EffectList: ...
    @overload
    def __getitem__(self, idx: int) -> Effect: ...
    def __getitem__(self, idx: int | slice) -> Effect | EffectList:
        return super().__getitem__(idx)  # type: ignore[return-value]


class Model(nn.Module):
    """Base class: normalisation buffers, compatibility checks and the rollout signature.

    What only the residual loop reads (represented effect kinds, a latent state, one-step predictions,
    interpretable parameters) is optional: the protocols of `mpsim.models.capabilities`.

    Args:
        state_dim: D, state variables per node.
        control_dim: C, control inputs per node (0 without controls).
        effects: named physical terms (`mpsim.effects`) with learnable coefficients that the model adds to
            its vector field (e.g. what `mpsim diagnose fix=true` found missing).

    Examples:
        A model that predicts that nothing moves (ready-made ones: `mpsim.models`, e.g. `MPNODE`):

        >>> from mpsim import Model, rollout, simulate
        >>> from mpsim.systems import CoupledPendulums
        >>> class Still(Model):
        ...     def rollout(self, x0, t, inputs):  # x0: [B, N, D] -> [B, T, N, D]
        ...         return x0.unsqueeze(1).expand(-1, len(t), -1, -1)
        >>> data = simulate(CoupledPendulums(), 2, horizon=5)
        >>> pred, _ = rollout(Still(state_dim=2), data)
        >>> bool((pred[:, -1] == data.x[:, 0].float()).all())
        True
    """

    #: whether a trained model can run on a graph with a different number of nodes
    transfers_across_graphs: bool = True
    #: observed states a rollout starts from: 1 = x0 [B, N, D]; K > 1 = the first K states [B, K, N, D]
    #: (forecasters that read a window); errors are then measured from step K on
    context_steps: int = 1

    @property
    def time_invariant(self) -> bool:
        """Whether a rollout depends on time only through the spacing of `t` and the inputs it is given (no drive
        by absolute time, no per-record phase): windows of a record may then be shifted to one time grid and
        rolled out as one batch (`mpsim.diagnose.windows`). False unless a model says so."""
        return False

    # buffers (nn.Module.__getattr__ would type them as Tensor | Module)
    state_mean: torch.Tensor
    state_std: torch.Tensor

    def __init__(self, state_dim: int, control_dim: int = 0, effects: Sequence[Effect] = ()) -> None:
        super().__init__()
        if state_dim < 1:
            raise IncompatibleError(f"a model needs state_dim >= 1; got {state_dim}.")
        self.state_dim, self.control_dim = int(state_dim), int(control_dim)
        self.effects = EffectList(effects)
        self.register_buffer("state_mean", torch.zeros(state_dim))
        self.register_buffer("state_std", torch.ones(state_dim))

    # ---- effects -------------------------------------------------------------------------------------
    def bind_effects(self, state_names: Sequence[str]) -> None:
        """Resolve the effects' target/source names against the data's state names."""
        for effect in self.effects:
            effect.bind(state_names)

    def bind_inputs(self, control_names: Sequence[str]) -> None:
        """Check the data's control names against the model's inputs; default: any (matched by position)."""

    def integrate(
        self,
        field: nn.Module,  # forward(t, y, history=None) -> dy/dt
        y0: torch.Tensor,  # [B, ...] initial state
        t: torch.Tensor,  # [T] output times
        solver: Any,
        past: torch.Tensor | None = None,  # [B, P, ...] recorded states before t[0] (delays' history), or None
    ) -> torch.Tensor:
        """[B, T, ...] the field integrated by `solver`, or by fixed-step RK4 with history when an effect is
        delayed (an ODE solver cannot read past states): the history before t[0] is `past` (then y0 before it),
        interpolated linearly. The RK4 step is a quarter of the sampling interval, shorter for a shorter delay but
        never below a sixteenth (a fitted delay that shrinks must not make the step vanish; a query inside the
        current step is then extrapolated from the last two states)."""
        delay = min_delay(self.effects)
        if delay > 0:
            step = float(t[1] - t[0]) / 4 if t.numel() > 1 else delay
            reach = max(delay, step / 4)
            return rk4_delay(lambda tt, yy, hist: field(tt, yy, hist), y0, t, step=step, min_delay=reach, past=past)
        return solver(field, y0, t)

    # ---- normalisation -------------------------------------------------------------------------------
    def set_normalisation(
        self,
        mean: torch.Tensor,  # [D] per-feature mean of the training states
        std: torch.Tensor,  # [D] per-feature standard deviation
    ) -> None:
        self.state_mean.copy_(mean.to(self.state_mean))
        self.state_std.copy_(std.to(self.state_std))

    def normalise(self, x: torch.Tensor) -> torch.Tensor:  # x: [..., D] raw states
        """[..., D] z-scored states."""
        return (x - self.state_mean) / self.state_std

    def denormalise(self, z: torch.Tensor) -> torch.Tensor:  # z: [..., D] z-scored states
        """[..., D] raw states."""
        return z * self.state_std + self.state_mean

    # ---- interface -----------------------------------------------------------------------------------
    def check_compatible(
        self, state_dim: int, control_dim: int, n_nodes: int, trained_nodes: int | None = None
    ) -> None:
        """Raise `IncompatibleError` when this model cannot run on data of the given shape."""
        name = type(self).__name__
        if state_dim != self.state_dim:
            raise IncompatibleError(
                f"{name} was built for {self.state_dim} state variables per node but the data has {state_dim}. "
                "Use a checkpoint trained on this system, or train from scratch (drop init=)."
            )
        if control_dim != self.control_dim:
            raise IncompatibleError(
                f"{name} was built for {self.control_dim} controls per node but the data has {control_dim}."
            )
        if not self.transfers_across_graphs and trained_nodes is not None and n_nodes != trained_nodes:
            raise IncompatibleError(
                f"{name} models the whole flattened state of {trained_nodes} nodes and cannot run on a graph of "
                f"{n_nodes} nodes. Use a modular model (model=mpnode) to transfer across graph sizes."
            )

    def rollout(
        self,
        x0: torch.Tensor,  # [B, N, D] initial states (raw units)
        t: torch.Tensor,  # [T] times, t[0] is the time of x0
        inputs: Inputs,  # graph [2, E] or [B, 2, E], controls [B, T, N, C], node features, meta
    ) -> torch.Tensor:
        """[B, T, N, D] predicted states (raw units), the first equal to x0.

        `inputs` holds the rest: `edge_index` (shared or per-trajectory graph, padded with -1), controls `u` on
        the grid `t`, static `node_features` (mass, charge) and the data's `meta` (e.g. box_size of a periodic
        domain); `Trajectories.inputs(start, stop)` makes it for a window of the data."""
        raise NotImplementedError

    def training_loss(
        self,
        batch: Trajectories,
        t: torch.Tensor,  # [T] times in the model's dtype
        loss_fn: Callable[..., torch.Tensor],
        delta: float = 1.0,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(loss, [B, T, N, D] prediction) for one batch. Default: MPNODE.jl's single shooting — a free
        rollout of the whole trajectory from its first state, loss on the normalised measured states
        (`Trajectories.observed_index`: a latent state, estimated rather than measured, starts the rollout but is
        no target). Models trained differently (one-step targets, windows) override this."""
        pred = self.rollout(self.initial(batch.x), t, batch.inputs())
        return self.observed_loss(loss_fn, pred, batch.x, batch.observed_index, delta), pred

    def observed_loss(
        self,
        loss_fn: Callable[..., torch.Tensor],
        pred: torch.Tensor,  # [B, T, N, D] predicted states (raw units)
        target: torch.Tensor,  # [B, T, N, D] data (raw units; latent columns estimated)
        observed: Sequence[int],  # the measured feature columns (`Trajectories.observed_index`)
        delta: float = 1.0,
    ) -> torch.Tensor:
        """`loss_fn` on the normalised states, the measured feature columns only."""
        return loss_fn(
            select_features(self.normalise(pred), observed), select_features(self.normalise(target), observed), delta
        )

    def initial(self, x: torch.Tensor) -> torch.Tensor:  # x: [B, T, N, D] observed trajectories
        """What a rollout starts from: [B, N, D] first states, or [B, K, N, D] with `context_steps` = K > 1."""
        return x[:, 0] if self.context_steps == 1 else x[:, : self.context_steps]

    def report(self) -> dict[str, Any]:
        """Model-specific results for summary.json (e.g. discovered equations); default: none."""
        return {}

    def report_lines(self) -> list[tuple[str, str]]:
        """(label, text) rows for the end-of-run summary on screen; default: none."""
        return []

    def after_step(self) -> None:
        """Called after every optimiser step (e.g. sparsity thresholding); default: nothing."""

    def rollout_aux(
        self,
        x0: torch.Tensor,  # [B, N, D] initial states
        t: torch.Tensor,  # [T] times
        inputs: Inputs,  # graph, controls [B, T, N, C], node features, meta (as `rollout`)
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Prediction plus internal signals worth plotting (e.g. MP-NODE messages); default: none."""
        return self.rollout(x0, t, inputs), {}

    def describe(self) -> dict[str, Any]:
        """Plain facts for summaries: class, parameter count."""
        return {"model": type(self).__name__, "n_params": sum(p.numel() for p in self.parameters())}
