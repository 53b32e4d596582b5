"""L2S: the MP-NODE paper's "Learning to Simulate" baseline, as MPNODE.jl runs it (`gnnsc_de0`).

A continuous-time graph-network ODE, not a discrete encode-process-decode with Euler steps: the ODE state is
the (z-scored) node state itself, and at every solver stage the right-hand side is

    h⁰_i = tanh(W_l [x_i; u_i] + b_l)                               lift (D + C → H)
    a_i  = Σ_{j ∈ N(i)} tanh(W_1 h_j + b_1)   (ψ if N(i) is empty)   sum aggregation, ψ ∈ R^H trainable
    h_i  ← tanh(W_2 a_i + b_2) + h_i                                 processor step (residual), `depth` times
    dx_i/dt = W_o (h^depth_i + h⁰_i) + b_o                           readout with a skip from the lift

Messages depend only on the sender (the paper's L2S without edge features); there is no hidden state
carried between steps, so all coupling has to be expressed through the instantaneous neighbour sum. With
H = 32 and D = 3 the model has 2371 parameters (ψ included), as in the reference. Each processor step has
its own weights. Normalisation: z-score per feature like MP-NODE (MPNODE.jl's L2S config used a "simple"
normalisation that, as shipped, mixes features; it is not reproduced).

Aggregation. The H-wide neighbour sum is the costly part of the right-hand side. On the small, dense graphs of
the paper's benchmarks (gene 8×8: BA(64, 32), half of all pairs connected) a batched product with a dense
[B, N, N] adjacency is ~25× faster than a gather/scatter over the edge list, so graphs of up to
`dense_max_nodes` nodes aggregate densely; larger ones keep the edge list (same result).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from mpsim.data.trajectories import Inputs
from mpsim.effects import Effect
from mpsim.graphs.batch import BatchedGraph, check_graph_mode, dense_adjacency, message_graph, sum_aggregate
from mpsim.models.controls import ControlledModel, ControlNormalisation, HeldField, integrate_held, zero_order_hold
from mpsim.models.layers import ACTIVATIONS, dense
from mpsim.solvers.odeint import ODESolver


class _ProcessorStep(nn.Module):
    """One residual message-passing round: sender-only messages, sum aggregation, trainable ψ."""

    def __init__(self, hidden: int, activation: type[nn.Module]) -> None:
        super().__init__()
        self.message, self.update, self.act = dense(hidden, hidden), dense(hidden, hidden), activation()
        self.psi = nn.Parameter(torch.zeros(hidden))  # aggregate of an empty neighbourhood (Mill's ψ, init 0)

    def forward(
        self,
        h: torch.Tensor,  # [B, N, H] node embeddings
        graph: BatchedGraph,
        empty: torch.Tensor,  # [B, N, 1] 1.0 where a node has no in-neighbours
        adjacency: torch.Tensor | None = None,  # [B, N, N] dense adjacency (None: aggregate over the edge list)
    ) -> torch.Tensor:
        """[B, N, H] the embeddings after one round."""
        messages = self.act(self.message(h))  # [B, N, H] depend on the sender only
        agg = adjacency @ messages if adjacency is not None else sum_aggregate(messages, graph)
        return self.act(self.update(agg + empty * self.psi)) + h


class _GraphField(HeldField):
    """dz/dt of every node of a batch: the graph, controls and their hold fixed for one rollout."""

    def __init__(
        self,
        model: L2S,
        graph: BatchedGraph,
        t_grid: torch.Tensor,  # [T] sample times of u
        u: torch.Tensor | None,  # [B, T, N, C] normalised controls
        dense_max_nodes: int = 128,
    ) -> None:
        super().__init__()
        self.model, self.graph, self.t_grid, self.u = model, graph, t_grid, u
        self.held: int | None = None  # control sample fixed by an interval-by-interval solve
        b, n = graph.n_graphs, graph.n_nodes
        self.empty = (graph.inv_degree == 0).to(graph.inv_degree.dtype).reshape(b, n, 1)  # [B, N, 1]
        self.adjacency = dense_adjacency(graph, self.empty.dtype) if n <= dense_max_nodes else None  # [B, N, N]

    def forward(self, t: torch.Tensor, z: torch.Tensor, history=None) -> torch.Tensor:  # t: [], z: [B, N, D]
        m = self.model
        u = zero_order_hold(self.t_grid, self.u, t, self.held)
        h0 = m.act(m.lift(z if u is None else torch.cat([z, u], dim=-1)))  # [B, N, H]
        h = h0
        for step in m.processor:  # `depth` rounds, each with its own weights
            h = step(h, self.graph, self.empty, self.adjacency)
        return m.readout(h + h0)


class L2S(ControlledModel):
    """Continuous-time graph-network ODE baseline (MPNODE.jl `gnnsc_de0`, the paper's L2S).

    Args:
        state_dim: D, state variables per node (set from the data).
        control_dim: C, controls per node (set from the data).
        hidden: embedding width H (reference: 32).
        depth: processor rounds per right-hand-side evaluation (reference: 1).
        activation: tanh (reference), relu, softplus, silu or gelu.
        self_loops: include each node among its own neighbours.
        graph: "data", the sum runs over the data's graph (MPNODE.jl `graph="sys"`), or "full": over all nodes,
            self included, whatever the data's graph (MPNODE.jl `graph="full"`, its shipped configs' setting).
        dense_max_nodes: graphs of at most this many nodes aggregate with a dense adjacency product (faster
            on small graphs); larger ones over the edge list.
        effects: named physical terms with learnable coefficients (not supported: must be empty).
        solver: how the vector field is integrated (default: dopri5, rtol = atol = 1e-4).
    """

    def __init__(
        self,
        state_dim: int,
        control_dim: int = 0,
        hidden: int = 32,
        depth: int = 1,
        activation: str = "tanh",
        self_loops: bool = False,
        dense_max_nodes: int = 128,
        effects: Sequence[Effect] = (),
        solver: ODESolver | None = None,
        graph: str = "data",
    ) -> None:
        if effects:
            raise ValueError("model=l2s does not take effects; use model=mpnode or model=physics for them.")
        super().__init__(state_dim, control_dim)
        if hidden < 1 or depth < 0 or activation not in ACTIVATIONS:
            raise ValueError(
                f"model.hidden must be >= 1, model.depth >= 0 and model.activation one of {sorted(ACTIVATIONS)}; "
                f"got {hidden}, {depth}, {activation!r}."
            )
        self.hidden, self.depth, self.self_loops, self.graph = (
            int(hidden),
            int(depth),
            bool(self_loops),
            check_graph_mode(graph),
        )
        self.dense_max_nodes = int(dense_max_nodes)
        self.solver = solver or ODESolver()
        self.act = ACTIVATIONS[activation]()
        self.lift = dense(state_dim + control_dim, hidden)
        self.processor = nn.ModuleList(_ProcessorStep(hidden, ACTIVATIONS[activation]) for _ in range(depth))
        self.readout = dense(hidden, state_dim)
        self.controls = ControlNormalisation(control_dim)

    def rollout(
        self,
        x0: torch.Tensor,  # [B, N, D] initial states (raw units)
        t: torch.Tensor,  # [T] times
        inputs: Inputs,  # graph (padded with −1), controls [B, T, N, C] (zero-order hold); nodes are identical
    ) -> torch.Tensor:
        b, n, _ = x0.shape
        graph = message_graph(inputs.edge_index.to(x0.device), b, n, self.graph, self.self_loops, x0.dtype)
        field = _GraphField(self, graph, t.to(x0), self.controls(inputs.u), self.dense_max_nodes)
        z = integrate_held(lambda f, y, tt: self.integrate(f, y, tt, self.solver), field, self.normalise(x0), t)
        return self.denormalise(z)
