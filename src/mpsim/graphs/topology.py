"""Graph topologies as `edge_index` tensors [2, E] of (sender, receiver) pairs.

Undirected graphs list both directions. Random families use networkx with an explicit seed so that a
graph is reproducible and can be stored with the data it generated.
"""

from __future__ import annotations

import networkx as nx
import torch

from mpsim.errors import ConfigError
from mpsim.memory import check_fits


def from_networkx(graph: nx.Graph) -> torch.Tensor:
    """`edge_index` [2, E] of a networkx graph with nodes 0..N-1 (both directions if undirected)."""
    edges = list(graph.edges())
    if not edges:
        return torch.zeros(2, 0, dtype=torch.long)
    e = torch.tensor(edges, dtype=torch.long).T
    if not graph.is_directed():
        loops = e[0] == e[1]
        e = torch.cat([e, e[:, ~loops].flip(0)], dim=1)
    return sort_edges(e)


def from_adjacency(adjacency: torch.Tensor) -> torch.Tensor:
    """`edge_index` [2, E] from a dense adjacency [N, N] where A[i, j] != 0 means an edge j -> i.

    The convention matches the ODE coupling `dx_i/dt = sum_j A_ij f(x_j)`: row = receiver.
    """
    receiver, sender = torch.nonzero(adjacency, as_tuple=True)
    return sort_edges(torch.stack([sender, receiver]))


def sort_edges(edge_index: torch.Tensor) -> torch.Tensor:
    """Edges [2, E] sorted by receiver, then sender (a canonical order for tests and storage)."""
    if edge_index.shape[1] == 0:
        return edge_index
    n = int(edge_index.max()) + 1
    order = torch.argsort(edge_index[1] * n + edge_index[0])
    return edge_index[:, order].contiguous()


def complete(n: int, self_loops: bool = False) -> torch.Tensor:
    """All-to-all graph on `n` nodes (`self_loops` adds i -> i)."""
    a = torch.ones(n, n)
    if not self_loops:
        a.fill_diagonal_(0)
    return from_adjacency(a)


def chain(n: int) -> torch.Tensor:
    """Path 0 - 1 - ... - (n-1)."""
    return from_networkx(nx.path_graph(n))


def ring(n: int) -> torch.Tensor:
    """Cycle 0 - 1 - ... - (n-1) - 0."""
    return from_networkx(nx.cycle_graph(n))


def grid(rows: int, cols: int) -> torch.Tensor:
    """4-neighbour grid; node id = row * cols + col."""
    g = nx.convert_node_labels_to_integers(nx.grid_2d_graph(rows, cols), ordering="sorted")
    return from_networkx(g)


def erdos_renyi(n: int, p: float | None = None, m: int | None = None, seed: int = 0) -> torch.Tensor:
    """G(n, p) when `p` is given, G(n, m edges) when `m` is given (the MPNODE.jl Kuramoto convention)."""
    if (p is None) == (m is None):
        raise ConfigError("erdos_renyi needs exactly one of p (edge probability) or m (edge count).")
    g = nx.gnp_random_graph(n, p, seed=seed) if p is not None else nx.gnm_random_graph(n, m, seed=seed)
    return from_networkx(g)


def barabasi_albert(n: int, k: int, seed: int = 0) -> torch.Tensor:
    """Barabási–Albert preferential attachment, `k` edges per new node."""
    return from_networkx(nx.barabasi_albert_graph(n, k, seed=seed))


def watts_strogatz(n: int, k: int, p: float, seed: int = 0) -> torch.Tensor:
    """Watts–Strogatz small world: ring lattice with `k` neighbours, rewiring probability `p`."""
    return from_networkx(nx.watts_strogatz_graph(n, k, p, seed=seed))


TOPOLOGIES = ("complete", "chain", "ring", "grid", "erdos_renyi", "barabasi_albert", "watts_strogatz")


def topology_bytes(kind: str, n: int, **kwargs) -> int:
    """Memory that building a topology takes, roughly: the dense [N, N] adjacency and its index for `complete`;
    networkx's dictionaries (about 1 kB per node and per edge) for the others."""
    if kind == "complete":
        return 40 * n * n
    k = int(kwargs.get("k") or 2)
    if kind == "erdos_renyi":
        edges = int(kwargs["m"]) if kwargs.get("m") is not None else int(float(kwargs.get("p") or 0) * n * n)
    else:
        edges = {"chain": 2, "ring": 2, "grid": 4, "barabasi_albert": 2 * k, "watts_strogatz": k}.get(kind, 2) * n
    return 1000 * (n + edges)


def make_topology(kind: str, n: int, **kwargs) -> torch.Tensor:
    """`edge_index` for a named topology; `kwargs` are the family's parameters (p, m, k, seed, rows...).

    Raises:
        ResourceError: building it would take more memory than there is (before anything is allocated).
    """
    if kind in TOPOLOGIES:
        check_fits(topology_bytes(kind, n, **kwargs), f"a {kind} graph on {n} nodes", fix="fewer nodes", forced=False)
    if kind == "complete":
        return complete(n, **kwargs)
    if kind == "chain":
        return chain(n)
    if kind == "ring":
        return ring(n)
    if kind == "grid":
        rows = kwargs.get("rows") or int(round(n**0.5))
        if n % rows:
            raise ConfigError(f"graph=grid needs n_nodes divisible by rows={rows}; got n_nodes={n}.")
        return grid(rows, n // rows)
    if kind == "erdos_renyi":
        return erdos_renyi(n, **kwargs)
    if kind == "barabasi_albert":
        return barabasi_albert(n, **kwargs)
    if kind == "watts_strogatz":
        return watts_strogatz(n, **kwargs)
    raise ConfigError(f"unknown graph kind {kind!r}; choose one of {', '.join(TOPOLOGIES)}.")
