"""Kuramoto oscillators on random graphs (MP-NODE paper's Kuramoto10; MPNODE.jl `kuramoto.jl`).

Each node carries D = 3 independent phases. Component c of node i is its own Kuramoto network on the shared
graph, coupled only to component c of its neighbours:

    θ̇_ic = ω_c + K Σ_j A_ij sin(θ_jc − θ_ic),      K = 1/3,

with one natural-frequency vector ω ~ N(0, I₃) shared by every node (homogeneous nodes), drawn from
`omega_seed` so that the BA, ER and WS systems share their node dynamics and a model can move between them.
Undirected edges: both endpoints feel the attractive term (NetworkDynamics' ``:undirected`` static edge).

Graphs (MPNODE.jl `simple_*_kuramoto10_5`): BA(10, 5) (25 edges), WS(10, 5, 0.5) (2 ring neighbours on each
side, 20 edges) and **ER with an edge count**: LightGraphs' `erdos_renyi(n, k::Int)` is G(n, m = k edges), not
G(n, p), so Kuramoto10 ER has only m = 5 edges and usually isolated nodes (which then rotate freely at ω).
`graph_params={p: 0.5}` gives G(n, p) instead.

Phases. The state is the unwrapped phase, exactly as integrated (MPNODE.jl does not wrap either): the flow
is smooth, so a neural ODE sees a continuous target, whereas wrapping into [−π, π) would put 2π jumps into
the data that no ODE can follow. Errors are measured on the circle (`meta["periods"]` = 2π per component),
so a prediction off by a whole turn, or data that arrive wrapped, is not counted as an error. sin/cos
features would need a model that keeps them on the unit circle and would double the state; they are not
used.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import torch

from mpsim.data.trajectories import Trajectories
from mpsim.errors import ConfigError
from mpsim.systems.base import System
from mpsim.systems.graph_ensemble import GraphEnsembleSystem


def default_kuramoto_graph_params(graph: str) -> dict[str, Any]:
    """MPNODE.jl's Kuramoto10_5 parameters: BA k = 5; ER m = 5 edges; WS k = 5, p = 0.5."""
    params: dict[str, dict[str, Any]] = {
        "erdos_renyi": {"m": 5},
        "barabasi_albert": {"k": 5},
        "watts_strogatz": {"k": 5, "p": 0.5},
    }
    return params.get(graph, {})


def natural_frequencies(dim: int, seed: int) -> torch.Tensor:
    """[dim] float64 ω ~ N(0, 1) from our own seed (Julia's MersenneTwister stream cannot be reproduced)."""
    return torch.randn(dim, generator=torch.Generator().manual_seed(int(seed)), dtype=torch.float64)


class Kuramoto(GraphEnsembleSystem, System):
    """Kuramoto oscillators with `dim` independent phase components per node; node state (θ1, θ2, θ3).

    Args:
        name: dataset/checkpoint name (``kuramoto10_ba``, ...).
        n_nodes: oscillators (reference: 10).
        dim: independent phase components per node (reference: 3).
        coupling: K (reference: 1/3).
        graph: ``erdos_renyi``, ``barabasi_albert`` or ``watts_strogatz``.
        graph_params: the family's parameters (None: MPNODE.jl's, see `default_kuramoto_graph_params`).
        graph_seed: seed of the first graph; graph g uses graph_seed + g.
        n_graphs: G, graphs in the ensemble (trajectory b runs on graph b mod G).
        omega_seed: seed of the shared natural frequencies ω.
        ic_range: uniform range of every initial phase.
        effects: extra terms added to the dynamics.
    """

    dt = 0.05
    horizon = 50

    def __init__(
        self,
        name: str = "kuramoto10_ba",
        n_nodes: int = 10,
        dim: int = 3,
        coupling: float = 1.0 / 3.0,
        graph: str = "barabasi_albert",
        graph_params: Mapping[str, Any] | None = None,
        graph_seed: int = 42,
        n_graphs: int = 1,
        omega_seed: int = 42,
        ic_range: Sequence[float] = (-1.0, 1.0),
        effects: Sequence[Any] = (),
    ) -> None:
        if n_nodes < 2 or dim < 1:
            raise ConfigError(f"system.n_nodes must be >= 2 and system.dim >= 1; got {n_nodes}, {dim}.")
        self.state_names = tuple(f"theta{c + 1}" for c in range(dim))  # per instance: D is a parameter
        params = default_kuramoto_graph_params(graph) if graph_params is None else graph_params
        first = self._init_graphs(n_nodes, graph, params, graph_seed, n_graphs)
        System.__init__(self, name, n_nodes, first, effects)
        self.dim, self.coupling, self.omega_seed = int(dim), float(coupling), int(omega_seed)
        self.omega = natural_frequencies(self.dim, self.omega_seed)  # [D]
        self.ic_range = tuple(float(v) for v in ic_range)

    def params(self) -> dict[str, Any]:
        return {
            "n_nodes": self.n_nodes,
            "dim": self.dim,
            "coupling": self.coupling,
            **self.graph_params_record(),
            "omega_seed": self.omega_seed,
            "omega": self.omega.tolist(),
            "ic_range": list(self.ic_range),
        }

    def meta(self, dt: float) -> dict[str, Any]:
        # phases: errors are taken on the circle, so wrapped data or a whole-turn offset is not an error
        return {**super().meta(dt), "periods": [2 * math.pi] * self.dim}

    def dynamics(
        self,
        t: torch.Tensor,  # [] time
        x: torch.Tensor,  # [B, N, D] phases (unwrapped)
        u: torch.Tensor | None = None,  # unused: no controls
    ) -> torch.Tensor:
        # Σ_j A_ij sin(θ_j − θ_i) = cos θ_i (A sin θ)_i − sin θ_i (A cos θ)_i: two matrix products, no edge loop
        a = self.batch_adjacency(x)  # [N, N] or [B, N, N]
        s, c = torch.sin(x), torch.cos(x)
        pull = c * (a @ s) - s * (a @ c)  # [B, N, D]
        return self.omega.to(x) + self.coupling * pull

    def sample_initial_states(self, n: int, generator: torch.Generator) -> torch.Tensor:
        lo, hi = self.ic_range
        return lo + (hi - lo) * torch.rand(n, self.n_nodes, self.dim, generator=generator, dtype=torch.float64)

    def simulate(
        self,
        x0: torch.Tensor,  # [B, N, D] initial phases
        t: torch.Tensor,  # [T] output times
        rtol: float = 1e-8,
        atol: float = 1e-10,
        method: str = "dopri5",
    ) -> Trajectories:
        """Integrate from `x0`; trajectory b runs on (and carries) graph b mod G."""
        return self.with_batch_graphs(super().simulate(x0, t, rtol, atol, method))
