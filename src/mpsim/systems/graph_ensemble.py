"""`GraphEnsembleSystem`: a system whose trajectories run on several random graphs of one family.

The MP-NODE paper trains its gene model on "five different adjacency matrices in the BA topology", and
MPNODE.jl's `*_multi` tasks stack trajectories of systems built from graph seeds 1..5, each trajectory
keeping its own graph. Here one system holds all G graphs: **trajectory b of any batch runs on graph
b mod G** (round robin), so a larger dataset extends a smaller one and the graph of a trajectory follows
from its position alone. Generated `Trajectories` carry that graph per trajectory (`edge_index` [B, 2, E],
padded with −1), so models, splits and the dataset cache never need the system to know which graph is which.

With G = 1 the system is an ordinary single-graph system (`edge_index` [2, E] shared by every trajectory).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from typing import Any

import torch

from mpsim.data.trajectories import Trajectories
from mpsim.effects import EffectContext
from mpsim.errors import ConfigError
from mpsim.graphs.topology import make_topology

#: random families and the keyword parameters `mpsim.graphs.topology` expects for each
FAMILIES = {"erdos_renyi": ("p", "m"), "barabasi_albert": ("k",), "watts_strogatz": ("k", "p")}


def graph_ensemble(
    family: str, n_nodes: int, params: Mapping[str, Any], seeds: Sequence[int]
) -> tuple[torch.Tensor, torch.Tensor]:
    """The graphs of one random family drawn with each of `seeds`.

    Args:
        family: ``erdos_renyi``, ``barabasi_albert`` or ``watts_strogatz`` (undirected graphs).
        n_nodes: N, nodes per graph.
        params: the family's parameters (ER: exactly one of ``p`` or ``m``; BA: ``k``; WS: ``k`` and ``p``).
        seeds: one seed per graph.

    Returns:
        ([G, 2, E_max] edge lists padded with −1, [G, N, N] float64 adjacency with A[g, i, j] = 1 for an
        edge j → i, i.e. rows are receivers as in ẋ_i = Σ_j A_ij f(x_j)).
    """
    if family not in FAMILIES:
        raise ConfigError(f"system.graph={family!r} is not a random family; choose one of {', '.join(FAMILIES)}.")
    unknown = set(params) - set(FAMILIES[family])
    if unknown:
        raise ConfigError(
            f"system.graph_params {sorted(unknown)} do not apply to {family}; it takes {list(FAMILIES[family])}."
        )
    if not seeds:
        raise ConfigError("system.n_graphs must be >= 1.")
    edges = [make_topology(family, n_nodes, **dict(params), seed=int(s)) for s in seeds]  # one call per graph
    e_max = max(e.shape[1] for e in edges)
    padded = torch.stack([torch.nn.functional.pad(e, (0, e_max - e.shape[1]), value=-1) for e in edges])
    adjacency = torch.zeros(len(seeds), n_nodes, n_nodes, dtype=torch.float64)
    g, _, k = torch.nonzero(padded[:, :1] >= 0, as_tuple=True)  # (graph, edge) of every real edge
    adjacency[g, padded[g, 1, k], padded[g, 0, k]] = 1.0
    return padded, adjacency


class GraphEnsembleSystem:
    """Mixin for a `System` on G random graphs of one family; trajectory b runs on graph b mod G.

    Subclasses call `_init_graphs` before `System.__init__` and use `batch_adjacency` in `dynamics`.
    """

    n_nodes: int
    effects: list
    name: str
    _contexts: dict

    def _init_graphs(
        self,
        n_nodes: int,
        graph: str,
        graph_params: Mapping[str, Any],
        graph_seed: int,
        n_graphs: int,
    ) -> torch.Tensor:
        """Draw the ensemble (seeds graph_seed, graph_seed + 1, ...); return graph 0's [2, E] edges."""
        if n_graphs < 1:
            raise ConfigError(f"system.n_graphs must be >= 1; got {n_graphs}.")
        self.graph, self.graph_params = graph, dict(graph_params)
        self.graph_seed, self.n_graphs = int(graph_seed), int(n_graphs)
        seeds = [self.graph_seed + g for g in range(self.n_graphs)]
        self.graph_edges, self.adjacency = graph_ensemble(graph, n_nodes, self.graph_params, seeds)
        self._batch_cache: dict[tuple, torch.Tensor] = {}
        first = self.graph_edges[0]
        return first[:, first[0] >= 0]

    def graph_params_record(self) -> dict[str, Any]:
        """The ensemble's description for `params()` (the edges themselves travel with the data)."""
        return {
            "graph": self.graph,
            "graph_params": dict(self.graph_params),
            "graph_seeds": [self.graph_seed + g for g in range(self.n_graphs)],
            "n_edges": [int((e[0] >= 0).sum()) for e in self.graph_edges],
        }

    def batch_edge_index(self, batch: int) -> torch.Tensor:
        """[B, 2, E_max] graph of each trajectory of a batch of `batch` (graph b mod G, padded with −1)."""
        return self.graph_edges[torch.arange(batch) % self.n_graphs]

    def batch_adjacency(self, like: torch.Tensor) -> torch.Tensor:
        """[N, N] shared adjacency (G = 1) or [B, N, N] one per trajectory, in `like`'s dtype and device.

        Args:
            like: [B, N, D] states of the batch.
        """
        key = (like.shape[0], like.dtype, like.device)
        if key not in self._batch_cache:
            a = self.adjacency.to(like)
            a = a[0] if self.n_graphs == 1 else a[torch.arange(like.shape[0], device=like.device) % self.n_graphs]
            self._batch_cache = {key: a}  # one entry: a run uses one batch size at a time
        return self._batch_cache[key]

    def _context(self, x: torch.Tensor, history: Callable | None = None) -> EffectContext:  # x: [B, N, D]
        """Effects couple each trajectory on its own graph."""
        key = (x.shape[0], x.device, x.dtype)
        if key not in self._contexts:
            ei = (
                self.graph_edges[0][:, self.graph_edges[0][0] >= 0]
                if self.n_graphs == 1
                else (self.batch_edge_index(x.shape[0]))
            )
            self._contexts[key] = EffectContext.for_batch(ei, x)
        return EffectContext(self._contexts[key].graph, history)

    def with_batch_graphs(self, traj: Trajectories) -> Trajectories:
        """`traj` with each trajectory's own graph ([B, 2, E]) when the ensemble has several graphs."""
        if self.n_graphs == 1:
            return traj
        return replace(traj, edge_index=self.batch_edge_index(len(traj)))
