import pytest
import torch

from mpsim.errors import ResourceError
from mpsim.graphs import batch_graph, mean_aggregate, sum_aggregate
from mpsim.graphs.topology import (
    chain,
    complete,
    erdos_renyi,
    from_adjacency,
    grid,
    make_topology,
    ring,
    topology_bytes,
)


def test_edge_counts():
    assert complete(4).shape == (2, 12)
    assert complete(3, self_loops=True).shape == (2, 9)
    assert chain(5).shape == (2, 8)
    assert ring(5).shape == (2, 10)
    assert grid(2, 3).shape == (2, 14)
    assert erdos_renyi(10, m=5, seed=1).shape == (2, 10)  # G(n, m edges), both directions


def test_from_adjacency_row_is_receiver():
    a = torch.zeros(3, 3)
    a[0, 2] = 1  # edge 2 -> 0
    assert from_adjacency(a).tolist() == [[2], [0]]


def _dense_mean(values, edge_index, n):
    a = torch.zeros(n, n)
    a[edge_index[1], edge_index[0]] = 1.0
    deg = a.sum(1, keepdim=True)
    return torch.where(deg > 0, a @ values / deg.clamp(min=1), torch.zeros_like(values))


def test_mean_aggregate_matches_dense_and_handles_isolated_nodes():
    ei = torch.tensor([[0, 1, 2, 1], [1, 0, 1, 2]])  # node 3 has no neighbours
    values = torch.randn(5, 4, 2)
    out = mean_aggregate(values, batch_graph(ei, 5, 4))
    expected = torch.stack([_dense_mean(v, ei, 4) for v in values])
    assert torch.allclose(out, expected, atol=1e-6)
    assert torch.all(out[:, 3] == 0)


def test_per_trajectory_graphs_padded():
    g0 = torch.tensor([[0, 1], [1, 0]])
    g1 = torch.tensor([[0, 2, 1], [2, 0, 0]])
    padded = torch.full((2, 2, 3), -1, dtype=torch.long)
    padded[0, :, :2], padded[1] = g0, g1
    values = torch.randn(2, 3, 1)
    out = sum_aggregate(values, batch_graph(padded, 2, 3))
    assert torch.allclose(out[0, :, 0], torch.stack([values[0, 1, 0], values[0, 0, 0], torch.tensor(0.0)]))
    assert torch.allclose(
        out[1, :, 0], torch.stack([values[1, 2, 0] + values[1, 1, 0], torch.tensor(0.0), values[1, 0, 0]])
    )


def test_self_loops_join_the_mean():
    ei = torch.tensor([[0], [1]])
    values = torch.tensor([[[2.0], [4.0]]])
    out = mean_aggregate(values, batch_graph(ei, 1, 2, self_loops=True))
    assert out[0, :, 0].tolist() == [2.0, 3.0]


def test_a_graph_too_large_for_memory_is_refused_before_anything_is_allocated():
    with pytest.raises(ResourceError, match="a chain graph on 100000000000 nodes needs about 300 TB"):
        make_topology("chain", 10**11)
    with pytest.raises(ResourceError, match="a complete graph on 10000000 nodes"):
        make_topology("complete", 10**7)
    assert topology_bytes("complete", 10) == 4000 and make_topology("complete", 10).shape == (2, 90)
