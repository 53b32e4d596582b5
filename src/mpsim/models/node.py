"""NODE: the monolithic neural-ODE baseline of MPNODE.jl (`ndeln4`; `nde4` without LayerNorm).

One network for the whole system: the z-scored node states are flattened to X ∈ R^{N·D} (controls to
U ∈ R^{N·C}) and

    dX/dt = W_3 · LN(tanh(W_2 · LN(tanh(W_1 [X; U] + b_1)) + b_2)) + b_3,     hidden width h = 32.

It ignores the graph and ties every weight to node positions, so it is built for one node count N and cannot
run on another graph size — the reason the paper needs MP-NODE for transfer. A checkpoint trained on N nodes
is refused on data with another N (`transfers_across_graphs = False`, checked before any data are built).

N is known only once the data are: the command layer's compatibility check (`check_compatible`, called with
the data's node count before weights are loaded or an optimiser is created) sizes the network, or pass
`n_nodes=` when building the model directly.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import nn

from mpsim.data.trajectories import Inputs
from mpsim.effects import Effect
from mpsim.errors import IncompatibleError
from mpsim.models.controls import ControlledModel, ControlNormalisation, HeldField, integrate_held, zero_order_hold
from mpsim.models.layers import ACTIVATIONS, dense
from mpsim.solvers.odeint import ODESolver


class _FlatField(HeldField):
    """dZ/dt of the flattened system state of one rollout (controls and their hold fixed)."""

    def __init__(
        self,
        net: nn.Module,
        t_grid: torch.Tensor,  # [T] sample times of u
        u: torch.Tensor | None,  # [B, T, N, C] normalised controls
    ) -> None:
        super().__init__()
        self.net, self.t_grid, self.u = net, t_grid, u
        self.held: int | None = None  # control sample fixed by an interval-by-interval solve

    def forward(self, t: torch.Tensor, z: torch.Tensor, history=None) -> torch.Tensor:  # t: [], z: [B, N, D]
        b, n, d = z.shape
        u = zero_order_hold(self.t_grid, self.u, t, self.held)
        flat = z.reshape(b, n * d) if u is None else torch.cat([z.reshape(b, n * d), u.reshape(b, -1)], dim=-1)
        return self.net(flat).reshape(b, n, d)


class NODE(ControlledModel):
    """Monolithic neural ODE on the flattened state of all N nodes (cannot change N).

    Args:
        state_dim: D, state variables per node (set from the data).
        control_dim: C, controls per node (set from the data).
        hidden: width h of both hidden layers (reference: 32).
        n_hidden_layers: hidden layers (reference: 2).
        layer_norm: LayerNorm after each hidden activation (``ndeln4``; false gives ``nde4``).
        activation: tanh (reference), relu, softplus, silu or gelu.
        n_nodes: N; None sizes the network at the first compatibility check (the command layer's).
        effects: not supported (must be empty).
        solver: how the vector field is integrated (default: dopri5, rtol = atol = 1e-4).
    """

    transfers_across_graphs = False

    def __init__(
        self,
        state_dim: int,
        control_dim: int = 0,
        hidden: int = 32,
        n_hidden_layers: int = 2,
        layer_norm: bool = True,
        activation: str = "tanh",
        n_nodes: int | None = None,
        effects: Sequence[Effect] = (),
        solver: ODESolver | None = None,
    ) -> None:
        if effects:
            raise ValueError("model=node does not take effects; use model=mpnode or model=physics for them.")
        super().__init__(state_dim, control_dim)
        if hidden < 1 or n_hidden_layers < 1 or activation not in ACTIVATIONS:
            raise ValueError(
                f"model.hidden and model.n_hidden_layers must be >= 1 and model.activation one of "
                f"{sorted(ACTIVATIONS)}; got {hidden}, {n_hidden_layers}, {activation!r}."
            )
        self.hidden, self.n_hidden_layers, self.layer_norm = int(hidden), int(n_hidden_layers), bool(layer_norm)
        self.activation = activation
        self.solver = solver or ODESolver()
        self.controls = ControlNormalisation(control_dim)
        self.n_nodes: int | None = None
        self.net: nn.Sequential | None = None
        if n_nodes is not None:
            self.build(int(n_nodes))

    def build(self, n_nodes: int) -> None:
        """Create the network for `n_nodes` nodes (on the device and dtype of the model's buffers)."""
        if n_nodes < 1:
            raise IncompatibleError(f"NODE needs at least one node; got {n_nodes}.")
        width_in = n_nodes * (self.state_dim + self.control_dim)
        layers: list[nn.Module] = []
        for k in range(self.n_hidden_layers):
            layers += [dense(width_in if k == 0 else self.hidden, self.hidden), ACTIVATIONS[self.activation]()]
            if self.layer_norm:
                layers.append(nn.LayerNorm(self.hidden, eps=1e-5))
        layers.append(dense(self.hidden, n_nodes * self.state_dim))
        self.net = nn.Sequential(*layers).to(self.state_mean)
        self.n_nodes = n_nodes

    def check_compatible(
        self, state_dim: int, control_dim: int, n_nodes: int, trained_nodes: int | None = None
    ) -> None:
        """Refuse another node count than the checkpoint's (or the built network's); size an unbuilt network."""
        super().check_compatible(state_dim, control_dim, n_nodes, trained_nodes)
        self._require(n_nodes)

    def _require(self, n_nodes: int) -> None:
        if self.net is None:
            self.build(n_nodes)
        elif n_nodes != self.n_nodes:
            raise IncompatibleError(
                f"NODE models the whole flattened state of {self.n_nodes} nodes and cannot run on a graph of "
                f"{n_nodes} nodes: its weights are tied to node positions. Use a modular model (model=mpnode, "
                "or model=l2s) to transfer across graph sizes, or train a NODE from scratch on this graph."
            )

    def rollout(
        self,
        x0: torch.Tensor,  # [B, N, D] initial states (raw units)
        t: torch.Tensor,  # [T] times
        inputs: Inputs,  # only controls [B, T, N, C] (zero-order hold); no graph: the network sees every node
    ) -> torch.Tensor:
        self._require(x0.shape[1])
        assert self.net is not None  # `_require` built it
        field = _FlatField(self.net, t.to(x0), self.controls(inputs.u))
        z = integrate_held(lambda f, y, tt: self.integrate(f, y, tt, self.solver), field, self.normalise(x0), t)
        return self.denormalise(z)

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "n_nodes": self.n_nodes}
