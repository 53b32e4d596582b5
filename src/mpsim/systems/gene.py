"""Gene regulatory dynamics on random graphs (MP-NODE paper §4; MPNODE.jl `gene_evolution.jl`, after NDCN).

Each node carries one expression level x_i and follows the Michaelis–Menten form

    ẋ_i = −b·x_i^f + Σ_j A_ij · x_j^h / (1 + x_j^h),      b = 1, f = 1, h = 2,

on an undirected Erdős–Rényi, Barabási–Albert or Watts–Strogatz graph of n = 16 ("4×4") or 64 ("8×8")
nodes. The "grid" only lays out initial states and plots; the coupling graph is the random one. Reference
graph parameters: ER G(n, p = 0.5), BA with n/2 edges per new node, WS with n/2 ring neighbours rewired
with probability 0.5. Datasets may span several graphs of one family (the paper trains on five BA
adjacency matrices, seeds 1..5): trajectory b runs on graph b mod G and carries its own graph.

``coupling=mean_field`` replaces every graph by its mean field, A_ij = k̄/n for all i, j (k̄: `mean_degree`, or
each graph's own mean degree), so ẋ_i = −b·x_i^f + k̄·mean_j x_j^h/(1 + x_j^h): every node receives the same
input, as in an MP-NODE whose messages are averaged over all nodes (``model.graph=full``). It is the closed-form
baseline that shows what a model that cannot see the graph can reach; the data still carry the drawn graphs.

Initial states (MPNODE.jl): ``uniform`` draws U(0, 50) per node; ``hotspot`` starts from zeros on the
√n × √n grid and fills 3 random rectangles with a value U(30, 50) each (a later rectangle overwrites an
earlier one), then flattens the grid column-major (node k sits at row k mod √n, column k div √n).
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

IC_KINDS = ("hotspot", "uniform")
COUPLINGS = ("graph", "mean_field")


def default_gene_graph_params(graph: str, n_nodes: int) -> dict[str, Any]:
    """MPNODE.jl's parameters: ER p = 0.5; BA k = n/2; WS k = n/2, p = 0.5."""
    params: dict[str, dict[str, Any]] = {
        "erdos_renyi": {"p": 0.5},
        "barabasi_albert": {"k": n_nodes // 2},
        "watts_strogatz": {"k": n_nodes // 2, "p": 0.5},
    }
    return params.get(graph, {})


def hotspot_states(
    n: int,
    side: int,
    generator: torch.Generator,
    n_spots: int = 3,
    value_range: Sequence[float] = (30.0, 50.0),
) -> torch.Tensor:
    """[n, side²] float64 hot-spot initial states, flattened column-major (MPNODE.jl `custom_init_state`).

    Each spot draws its corner (sx, sy) ~ U(0.1, 0.9), its far corner e = min(s + U(0.1, 0.2), 1) and a
    value ~ U(value_range); it fills the 1-based inclusive block rows ⌈sx·side⌉..⌈ex·side⌉, columns
    ⌈sy·side⌉..⌈ey·side⌉. Spots are applied in order, so a later one overwrites an earlier one.
    """
    f64 = torch.float64
    start = 0.1 + 0.8 * torch.rand(n, n_spots, 2, generator=generator, dtype=f64)  # [n, S, (x, y)]
    end = torch.clamp(start + 0.1 + 0.1 * torch.rand(n, n_spots, 2, generator=generator, dtype=f64), max=1.0)
    lo, hi = value_range
    value = lo + (hi - lo) * torch.rand(n, n_spots, generator=generator, dtype=f64)  # [n, S]
    first, last = torch.ceil(start * side), torch.ceil(end * side)  # [n, S, 2] 1-based inclusive bounds
    idx = torch.arange(1, side + 1, dtype=f64)  # [side]
    in_rows = (idx >= first[..., 0:1]) & (idx <= last[..., 0:1])  # [n, S, side]
    in_cols = (idx >= first[..., 1:2]) & (idx <= last[..., 1:2])  # [n, S, side]
    covered = in_rows[..., :, None] & in_cols[..., None, :]  # [n, S, row, col]
    # the last spot covering a cell wins: its 1-based order, 0 where no spot covers the cell
    order = torch.arange(1, n_spots + 1, dtype=torch.long)[None, :, None, None]
    winner = (covered.long() * order).amax(dim=1)  # [n, row, col]
    padded = torch.cat([torch.zeros(n, 1, dtype=f64), value], dim=1)  # [n, 1 + S]: index 0 = no spot
    grid = torch.gather(padded, 1, winner.reshape(n, -1)).reshape(n, side, side)  # [n, row, col]
    return grid.transpose(1, 2).reshape(n, side * side)  # column-major flattening, as in Julia


class GeneRegulation(GraphEnsembleSystem, System):
    """Gene regulatory dynamics ẋ_i = −b x_i^f + Σ_j A_ij x_j^h/(1 + x_j^h); node state (x,).

    Args:
        name: dataset/checkpoint name (``gene_ba_small``, ...).
        n_nodes: n (16 for "4×4", 64 for "8×8"); must be a square for hot-spot initial states.
        graph: ``erdos_renyi``, ``barabasi_albert`` or ``watts_strogatz``.
        graph_params: the family's parameters (None: MPNODE.jl's, see `default_gene_graph_params`).
        graph_seed: seed of the first graph; graph g uses graph_seed + g.
        n_graphs: G, graphs in the ensemble (trajectory b runs on graph b mod G).
        b, f, h: decay rate, decay exponent and Hill exponent (reference: 1, 1, 2).
        initial: ``hotspot`` or ``uniform``.
        ic_range: range of the uniform initial states.
        hotspot_range: range of a hot spot's value.
        n_hotspots: hot spots per initial state.
        coupling: ``graph`` (the drawn graphs) or ``mean_field`` (each graph replaced by its mean field).
        mean_degree: k̄ of the mean field (None: each graph's own mean degree), e.g. the training family's
            for a zero-shot comparison.
        effects: extra terms added to the dynamics.
    """

    state_names = ("x",)
    dt = 0.05
    horizon = 50

    def __init__(
        self,
        name: str = "gene_ba_small",
        n_nodes: int = 16,
        graph: str = "barabasi_albert",
        graph_params: Mapping[str, Any] | None = None,
        graph_seed: int = 1,
        n_graphs: int = 5,
        b: float = 1.0,
        f: float = 1.0,
        h: float = 2.0,
        initial: str = "hotspot",
        ic_range: Sequence[float] = (0.0, 50.0),
        hotspot_range: Sequence[float] = (30.0, 50.0),
        n_hotspots: int = 3,
        coupling: str = "graph",
        mean_degree: float | None = None,
        effects: Sequence[Any] = (),
    ) -> None:
        if n_nodes < 2:
            raise ConfigError(f"system.n_nodes must be >= 2; got {n_nodes}.")
        if initial not in IC_KINDS:
            raise ConfigError(f"system.initial={initial!r} is unknown; choose one of {', '.join(IC_KINDS)}.")
        side = math.isqrt(n_nodes)
        if initial == "hotspot" and side * side != n_nodes:
            raise ConfigError(
                f"system.initial=hotspot lays the nodes on a square grid; n_nodes={n_nodes} is not a square "
                "(use 16 or 64, or system.initial=uniform)."
            )
        if coupling not in COUPLINGS:
            raise ConfigError(f"system.coupling={coupling!r} is unknown; choose one of {', '.join(COUPLINGS)}.")
        if mean_degree is not None and not mean_degree > 0:
            raise ConfigError(f"system.mean_degree must be > 0 (or null: each graph's own); got {mean_degree}.")
        params = default_gene_graph_params(graph, n_nodes) if graph_params is None else graph_params
        first = self._init_graphs(n_nodes, graph, params, graph_seed, n_graphs)
        self.coupling, self.mean_degree = coupling, None if mean_degree is None else float(mean_degree)
        if coupling == "mean_field":
            own = self.adjacency.sum(dim=(1, 2)) / n_nodes  # [G] each graph's mean degree
            k = own if self.mean_degree is None else torch.full_like(own, self.mean_degree)  # [G]
            self.adjacency = (k / n_nodes)[:, None, None].expand(-1, n_nodes, n_nodes).contiguous()  # [G, N, N]
        System.__init__(self, name, n_nodes, first, effects)
        self.b, self.f, self.h = float(b), float(f), float(h)
        self.initial, self.side = initial, side
        self.ic_range = tuple(float(v) for v in ic_range)
        self.hotspot_range = tuple(float(v) for v in hotspot_range)
        self.n_hotspots = int(n_hotspots)

    def params(self) -> dict[str, Any]:
        return {
            "n_nodes": self.n_nodes,
            **self.graph_params_record(),
            "b": self.b,
            "f": self.f,
            "h": self.h,
            "initial": self.initial,
            "ic_range": list(self.ic_range),
            "hotspot_range": list(self.hotspot_range),
            "n_hotspots": self.n_hotspots,
            "coupling": self.coupling,
            # the mean field's k̄ per graph (a list, so model=physics does not take it for a learnable constant)
            "mean_degree": self.adjacency.sum(dim=(1, 2)).div(self.n_nodes).tolist()
            if self.coupling != "graph"
            else None,
        }

    def dynamics(
        self,
        t: torch.Tensor,  # [] time
        x: torch.Tensor,  # [B, N, 1] expression levels
        u: torch.Tensor | None = None,  # unused: no controls
    ) -> torch.Tensor:
        # x stays >= 0 from non-negative starts (the decay vanishes at 0 and the input is >= 0); the clamp
        # only keeps fractional powers defined if a solver stage undershoots
        xp = x.clamp_min(0.0)
        activation = xp.pow(self.h) / (1.0 + xp.pow(self.h))  # [B, N, 1] each sender's regulatory output
        return -self.b * xp.pow(self.f) + self.batch_adjacency(x) @ activation

    def sample_initial_states(self, n: int, generator: torch.Generator) -> torch.Tensor:
        if self.initial == "uniform":
            lo, hi = self.ic_range
            return lo + (hi - lo) * torch.rand(n, self.n_nodes, 1, generator=generator, dtype=torch.float64)
        return hotspot_states(n, self.side, generator, self.n_hotspots, self.hotspot_range)[..., None]

    def simulate(
        self,
        x0: torch.Tensor,  # [B, N, 1] initial expression levels
        t: torch.Tensor,  # [T] output times
        rtol: float = 1e-8,
        atol: float = 1e-10,
        method: str = "dopri5",
    ) -> Trajectories:
        """Integrate from `x0`; trajectory b runs on (and carries) graph b mod G."""
        return self.with_batch_graphs(super().simulate(x0, t, rtol, atol, method))
