"""Batched graphs and neighbour aggregation without Python loops over nodes or edges.

A batch of B graphs on N nodes each is flattened to one graph on B*N nodes (node b*N + i), so one
`index_add_` aggregates every trajectory at once, whether the graph is shared or per trajectory.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from mpsim.graphs.topology import complete


@dataclass(frozen=True)
class BatchedGraph:
    """B copies (or B different graphs) of N nodes flattened to B*N nodes.

    Attributes:
        src: [E'] sender ids in 0..B*N-1.
        dst: [E'] receiver ids in 0..B*N-1.
        n_graphs: B.
        n_nodes: N nodes per graph.
        inv_degree: [B*N, 1] 1 / in-degree (0 where a node has no neighbours: its mean is 0).
    """

    src: torch.Tensor
    dst: torch.Tensor
    n_graphs: int
    n_nodes: int
    inv_degree: torch.Tensor

    @property
    def n_total(self) -> int:
        return self.n_graphs * self.n_nodes


def batch_graph(
    edge_index: torch.Tensor,  # [2, E] shared, or [B, 2, E] per graph padded with -1
    n_graphs: int,
    n_nodes: int,
    self_loops: bool = False,
    dtype: torch.dtype = torch.float32,
) -> BatchedGraph:
    """Flatten a shared or per-trajectory graph to one block-diagonal graph on `n_graphs * n_nodes` nodes."""
    device = edge_index.device
    offsets = torch.arange(n_graphs, device=device) * n_nodes  # [B]
    if edge_index.dim() == 2:
        src = (edge_index[0][None, :] + offsets[:, None]).reshape(-1)
        dst = (edge_index[1][None, :] + offsets[:, None]).reshape(-1)
    else:
        if edge_index.shape[0] != n_graphs:
            raise ValueError(f"expected {n_graphs} graphs in edge_index [B, 2, E]; got {edge_index.shape[0]}.")
        keep = (edge_index[:, 0] >= 0).reshape(-1)
        src = (edge_index[:, 0] + offsets[:, None]).reshape(-1)[keep]
        dst = (edge_index[:, 1] + offsets[:, None]).reshape(-1)[keep]
    if self_loops:
        loops = torch.arange(n_graphs * n_nodes, device=device)
        not_loop = src != dst
        src = torch.cat([src[not_loop], loops])
        dst = torch.cat([dst[not_loop], loops])
    inv = inverse_degree(dst, n_graphs * n_nodes, dtype)
    return BatchedGraph(src=src, dst=dst, n_graphs=n_graphs, n_nodes=n_nodes, inv_degree=inv)


#: the graph a model passes messages on: "data", the data's own graph (MPNODE.jl graph="sys"), or "full",
#: all-to-all with self-loops whatever the data's graph (MPNODE.jl graph="full", its shipped configs' setting)
GRAPH_MODES = ("data", "full")


def message_graph(
    edge_index: torch.Tensor,  # [2, E] shared, or [B, 2, E] per graph padded with -1: the data's graph
    n_graphs: int,
    n_nodes: int,
    mode: str = "data",
    self_loops: bool = False,
    dtype: torch.dtype = torch.float32,
) -> BatchedGraph:
    """`batch_graph` of the graph a model passes messages on (see `GRAPH_MODES`)."""
    if check_graph_mode(mode) == "full":
        edge_index = complete(n_nodes, self_loops=True).to(edge_index.device)
    return batch_graph(edge_index, n_graphs, n_nodes, self_loops=self_loops, dtype=dtype)


def check_graph_mode(mode: str) -> str:
    """`mode` if it is one of `GRAPH_MODES`; a ValueError naming `model.graph` otherwise."""
    if mode not in GRAPH_MODES:
        raise ValueError(f'model.graph must be one of {list(GRAPH_MODES)}; got "{mode}".')
    return mode


def inverse_degree(
    dst: torch.Tensor,  # [E] receiver of each edge
    n_nodes: int,
    dtype: torch.dtype,
) -> torch.Tensor:
    """[n_nodes, 1] 1 / in-degree of each node (0 for a node without in-neighbours)."""
    degree = segment_sum(torch.ones_like(dst, dtype=dtype), dst, n_nodes)
    return torch.where(degree > 0, 1.0 / degree.clamp(min=1), torch.zeros_like(degree))[:, None]


def segment_sum(
    values: torch.Tensor,  # [E, ...] per-edge (or per-member) values
    index: torch.Tensor,  # [E] segment of each row
    n_segments: int,
) -> torch.Tensor:
    """[n_segments, ...] sums of the rows of `values` per segment (zeros for an empty segment): the one
    scatter-sum of mpsim (graph aggregations, cell sums of a hierarchy, the graph-network blocks)."""
    return values.new_zeros(n_segments, *values.shape[1:]).index_add(0, index, values)


def mean_aggregate(
    values: torch.Tensor,  # [B, N, F] per-node values (e.g. outgoing messages)
    graph: BatchedGraph,
) -> torch.Tensor:
    """[B, N, F] mean over each node's in-neighbours of `values` (0 for a node with no neighbours)."""
    b, n, f = values.shape
    flat = values.reshape(b * n, f)
    out = segment_sum(flat.index_select(0, graph.src), graph.dst, b * n)
    return (out * graph.inv_degree.to(values.dtype)).reshape(b, n, f)


def dense_adjacency(graph: BatchedGraph, dtype: torch.dtype) -> torch.Tensor:
    """[B, N, N] adjacency of a batched graph, A[b, i, j] = number of edges j → i (rows are receivers).

    `A @ values` is `sum_aggregate(values, graph)` and `inv_degree`-scaled rows give `mean_aggregate`: on small,
    dense graphs (gene 8×8 is BA(64, 32), half of all pairs connected) one batched product is several times
    faster than a gather/scatter over the edge list."""
    b, n = graph.n_graphs, graph.n_nodes
    # node ids are b·N + i, so the flat index of (b, i, j) is (b·N + i)·N + j = dst·N + (src mod N)
    flat = segment_sum(torch.ones_like(graph.dst, dtype=dtype), graph.dst * n + graph.src % n, b * n * n)
    return flat.reshape(b, n, n)


def sum_aggregate(
    values: torch.Tensor,  # [B, N, F] per-node values
    graph: BatchedGraph,
) -> torch.Tensor:
    """[B, N, F] sum over each node's in-neighbours of `values`."""
    b, n, f = values.shape
    flat = values.reshape(b * n, f)
    return segment_sum(flat.index_select(0, graph.src), graph.dst, b * n).reshape(b, n, f)
