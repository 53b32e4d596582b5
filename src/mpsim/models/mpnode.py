"""MP-NODE: one shared neural ODE per node plus message variables averaged over graph neighbours.

Each node k carries its state x_k ∈ R^D and a message m_k ∈ R^M (zero at t0 of every trajectory). Inside
the ODE right-hand side, i.e. at every solver stage,

    m'_k = mean_{j ∈ N(k)} m_j          (0 for a node without neighbours; `aggregation=sum`: the sum)
    d/dt [x_k; m_k] = f_θ([x_k; u_k; m'_k])

with f_θ a tanh MLP shared by all nodes (Sanchez/Gupta et al., "Learning Modular Simulations for
Homogeneous Systems"; MPNODE.jl `EMPDynamicsModel`). Only x is supervised; messages evolve freely. The
node's own message is not an input unless `self_loops=true`. `graph="full"` ignores the data's graph and passes
messages all-to-all with self-loops, as every config MPNODE.jl ships does (its `graph="full"`). Because f_θ does
not depend on the number of nodes, a checkpoint trained on one graph runs on any other.

Graphs of at most `dense_max_nodes` nodes aggregate with one batched product by a dense [B, N, N] adjacency
(rows scaled by 1/degree for the mean), larger ones by a gather/scatter over the edge list: the same numbers to
rounding, and on the paper's dense gene 8×8 graphs (BA(64, 32)) a 1.75× faster rollout and backward (`mpsim bench
bench=mpnode bench.graph=ba`, which times both).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from mpsim.data.trajectories import Inputs
from mpsim.effects import Effect, EffectContext, total
from mpsim.graphs.batch import (
    BatchedGraph,
    batch_graph,
    check_graph_mode,
    dense_adjacency,
    mean_aggregate,
    message_graph,
    sum_aggregate,
)
from mpsim.models.controls import ControlledModel, ControlNormalisation, HeldField, integrate_held, zero_order_hold
from mpsim.models.layers import mlp
from mpsim.solvers.odeint import ODESolver

AGGREGATIONS = {"mean": mean_aggregate, "sum": sum_aggregate}


class _MessagePassingField(HeldField):
    """The augmented vector field of one rollout: graph and controls fixed, `net` shared."""

    def __init__(
        self,
        net: nn.Module,
        graph: BatchedGraph,
        state_dim: int,
        zero_messages: bool,
        t_grid: torch.Tensor,  # [T] sample times of u
        u: torch.Tensor | None = None,  # [B, T, N, C] controls (z-scored by the model)
        model: MPNODE | None = None,  # for its effects and normalisation
        effect_graph: BatchedGraph | None = None,  # the data's coupling graph (no self-loops) for effects
        aggregation: str = "mean",
        dense_max_nodes: int = 128,
    ) -> None:
        super().__init__()
        self.net, self.graph, self.state_dim, self.zero_messages = net, graph, state_dim, zero_messages
        self.aggregate = AGGREGATIONS[aggregation]
        # [B, N, N] the transposed adjacency, rows = senders, scaled by the receiver's 1/degree for the mean (None:
        # the edge list): m' = A m is computed as (mᵀ Aᵀ)ᵀ, whose batched product is ~5× faster with M = 3 columns
        self.adjacency_t = None
        if graph.n_nodes <= dense_max_nodes and not zero_messages:
            a = dense_adjacency(graph, t_grid.dtype)
            scale = graph.inv_degree.to(a.dtype).reshape(graph.n_graphs, graph.n_nodes, 1)
            self.adjacency_t = (a * scale if aggregation == "mean" else a).transpose(1, 2).contiguous()
        self.t_grid, self.u = t_grid, u
        self.held: int | None = None  # control sample fixed by an interval-by-interval solve
        self.model, self.effect_graph = model, effect_graph

    def controls_at(self, t: torch.Tensor) -> torch.Tensor | None:  # t: [] time
        """[B, N, C] zero-order-hold controls: the sample at or before `t`."""
        return zero_order_hold(self.t_grid, self.u, t, self.held)

    def forward(self, t: torch.Tensor, y: torch.Tensor, history=None) -> torch.Tensor:  # t: [], y: [B, N, D+M]
        x, m = y[..., : self.state_dim], y[..., self.state_dim :]
        if self.zero_messages:
            incoming = torch.zeros_like(m)
        elif self.adjacency_t is not None:
            incoming = torch.bmm(m.transpose(1, 2), self.adjacency_t).transpose(1, 2)
        else:
            incoming = self.aggregate(m, self.graph)
        u = self.controls_at(t)
        inputs = [x, incoming] if u is None else [x, u, incoming]
        dy = self.net(torch.cat(inputs, dim=-1))
        model = self.model
        if model is None or not len(model.effects):
            return dy
        assert self.effect_graph is not None  # the model builds it whenever it has effects
        # effects act on raw states; the network works in z-scored ones: dz/dt = (dx/dt) / std
        d = self.state_dim
        raw_history = None if history is None else (lambda s: model.denormalise(history(s)[..., :d]))
        extra = total(model.effects, t, model.denormalise(x), EffectContext(self.effect_graph, raw_history))
        return dy + torch.cat([extra / model.state_std, torch.zeros_like(m)], dim=-1)


class MPNODE(ControlledModel):
    """Message-passing neural ODE.

    The node MLP can learn any smooth function of the node's state and, through messages, of its
    neighbours', so the residual loop treats state-dependent effects as within its reach and looks for what
    it cannot express: explicit time dependence (forcing) and history (delays).

    Args:
        state_dim: D, state variables per node (set from the data).
        control_dim: C, controls per node (set from the data).
        hidden: width H of the node MLP (paper: 32).
        message_size: M, message variables per node (paper: 3).
        n_hidden_layers: hidden layers of the node MLP (paper: 2).
        activation: tanh (paper), relu, softplus, silu or gelu.
        zero_messages: replace incoming messages by zeros (the paper's "messages off" ablation; can be
            switched on a trained model to see what the messages carry).
        self_loops: include each node's own message in its mean.
        aggregation: "mean" of the neighbours' messages (paper, MPNODE.jl's SegmentedMean) or their "sum", which
            lets the node see how many neighbours it has (coupling that adds up over neighbours, e.g. gene
            regulation, whose strength a mean cannot tell apart across node degrees).
        graph: "data", the messages follow the data's graph (MPNODE.jl `graph="sys"`), or "full": all-to-all
            with self-loops whatever the data's graph (MPNODE.jl `graph="full"`; named effects still follow
            the data's graph).
        effects: named physical terms with learnable coefficients added to the node dynamics.
        dense_max_nodes: graphs of at most this many nodes aggregate with a dense adjacency product (faster on
            small graphs, the same numbers to rounding); larger ones over the edge list (0: always the list).
        solver: how the vector field is integrated (default: dopri5, rtol = atol = 1e-4).
    """

    represents = ("Bias", "LinearDamping", "QuadraticDrag", "CubicStiffness", "DiffusiveCoupling", "SineCoupling")
    represents_polynomials = 2
    # along a deterministic trajectory a delayed state x(t − τ) is a (complicated) function of the current
    # state, which a neural ODE can learn: against it a delay is indistinguishable from training error
    indistinguishable = ("DelayedFeedback",)
    #: one-step residuals restart the messages at zero every this many steps (the training window), see
    #: `mpsim.models.capabilities.LatentState` (None: carry them throughout)
    latent_reset: int | None = None

    def __init__(
        self,
        state_dim: int,
        control_dim: int = 0,
        hidden: int = 32,
        message_size: int = 3,
        n_hidden_layers: int = 2,
        activation: str = "tanh",
        zero_messages: bool = False,
        self_loops: bool = False,
        effects: Sequence[Effect] = (),
        solver: ODESolver | None = None,
        aggregation: str = "mean",
        graph: str = "data",
        dense_max_nodes: int = 128,
    ) -> None:
        super().__init__(state_dim, control_dim, effects)
        if aggregation not in AGGREGATIONS:
            raise ValueError(f'model.aggregation must be one of {sorted(AGGREGATIONS)}; got "{aggregation}".')
        self.aggregation, self.graph = aggregation, check_graph_mode(graph)
        if message_size < 0 or hidden < 1 or n_hidden_layers < 1:
            raise ValueError(
                f"model.message_size must be >= 0, model.hidden and model.n_hidden_layers >= 1; got "
                f"{message_size}, {hidden}, {n_hidden_layers}."
            )
        self.message_size, self.zero_messages, self.self_loops = (
            int(message_size),
            bool(zero_messages),
            bool(self_loops),
        )
        self.dense_max_nodes = int(dense_max_nodes)
        self.solver = solver or ODESolver()
        width = state_dim + control_dim + message_size
        self.net = mlp(width, hidden, state_dim + message_size, n_hidden_layers, activation)
        # controls enter the node MLP z-scored (raw rotor thrusts are 3.3 ± 0.2 N: nearly constant inputs);
        # no buffers without controls, so control-free checkpoints are unchanged
        self.controls = ControlNormalisation(control_dim)

    def _field(
        self,
        x: torch.Tensor,  # [B, ..., N, D] states of the batch (for its sizes, device and dtype)
        t: torch.Tensor,  # [T] times
        inputs: Inputs,  # graph [2, E] or [B, 2, E], controls [B, T, N, C]
    ) -> _MessagePassingField:
        """The vector field of one batch: its message graph, the data's graph for effects, controls."""
        b, n, d = x.shape[0], x.shape[-2], x.shape[-1]
        edge_index = inputs.edge_index.to(x.device)
        graph = message_graph(edge_index, b, n, self.graph, self.self_loops, x.dtype)
        effect_graph = batch_graph(edge_index, b, n, dtype=x.dtype) if len(self.effects) else None
        return _MessagePassingField(
            self.net, graph, d, self.zero_messages, t.to(x), self.controls(inputs.u), self, effect_graph,
            self.aggregation, dense_max_nodes=self.dense_max_nodes,
        )  # fmt: skip

    def rollout_aux(
        self,
        x0: torch.Tensor,  # [B, N, D] initial states (raw units)
        t: torch.Tensor,  # [T] times
        inputs: Inputs,  # graph [2, E] or [B, 2, E], controls [B, T, N, C]; nodes are identical
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        b, n, d = x0.shape
        y0 = torch.cat([self.normalise(x0), x0.new_zeros(b, n, self.message_size)], dim=-1)
        field = self._field(x0, t, inputs)
        # with controls, one solve per sample interval with the input held (see mpsim.models.controls)
        ys = integrate_held(lambda f, y, tt: self.integrate(f, y, tt, self.solver), field, y0, t)  # [B, T, N, D+M]
        return self.denormalise(ys[..., :d]), {"messages": ys[..., d:]}

    def one_step(
        self,
        x: torch.Tensor,  # [B, T, N, D] observed states (raw units)
        t: torch.Tensor,  # [T] times
        inputs: Inputs,  # graph [2, E] or [B, 2, E], controls [B, T, N, C] on the grid t; nodes are identical
    ) -> torch.Tensor:
        """One-step predictions along an observed trajectory with the messages carried from step to step
        (starting at zero at t0, as in a rollout, and again every `latent_reset` steps if set), so each step
        sees the latent state a rollout would."""
        b, n_t, n, d = x.shape
        u = inputs.u
        field = self._field(x, t, inputs)
        messages = x.new_zeros(b, n, self.message_size)
        preds = []
        for k in range(n_t - 1):  # sequential in time: the messages carry over
            if self.latent_reset and k % self.latent_reset == 0:
                messages = torch.zeros_like(messages)  # as at the start of a training window
            y0 = torch.cat([self.normalise(x[:, k]), messages], dim=-1)
            field.held = None if u is None else k  # the input of this interval is its first sample
            y1 = self.integrate(field, y0, t[k : k + 2].to(x), self.solver)[:, 1]
            preds.append(self.denormalise(y1[..., :d]))
            messages = y1[..., d:]
        return torch.stack(preds, dim=1)

    def rollout(
        self,
        x0: torch.Tensor,  # [B, N, D] initial states (raw units)
        t: torch.Tensor,  # [T] times
        inputs: Inputs,  # graph [2, E] or [B, 2, E], controls [B, T, N, C]; nodes are identical
    ) -> torch.Tensor:
        return self.rollout_aux(x0, t, inputs)[0]
