"""The graph a model passes messages on."""

import pytest
import torch

from mpsim.graphs.batch import batch_graph, dense_adjacency, message_graph, sum_aggregate


def test_full_message_graph_is_all_to_all_with_self_loops_whatever_the_data_graph():
    data = torch.tensor([[0, 1], [1, 0]])  # one edge each way on 3 nodes
    full = message_graph(data, 2, 3, mode="full")
    pairs = sorted(zip(full.src.tolist(), full.dst.tolist(), strict=True))
    assert pairs == sorted((g * 3 + i, g * 3 + j) for g in range(2) for i in range(3) for j in range(3))
    assert torch.allclose(full.inv_degree, torch.full((6, 1), 1 / 3))
    assert message_graph(data, 2, 3).src.numel() == 4  # "data": the data's own edges in each of the 2 graphs
    with pytest.raises(ValueError, match="model.graph"):
        message_graph(data, 2, 3, mode="sys")


def test_dense_adjacency_counts_edges_into_each_receiver_and_its_product_is_the_sum():
    # per-trajectory graphs padded with -1: a directed edge 0 -> 1 in the first, a 2-cycle and an isolated node in
    # the second; rows are receivers, so A[b, i, j] = 1 for an edge j -> i
    padded = torch.tensor([[[0, -1], [1, -1]], [[0, 1], [1, 0]]])
    a = dense_adjacency(batch_graph(padded, 2, 3), torch.float64)
    expected = torch.zeros(2, 3, 3, dtype=torch.float64)
    expected[0, 1, 0] = expected[1, 1, 0] = expected[1, 0, 1] = 1
    assert torch.equal(a, expected)
    values = torch.randn(4, 5, 3, dtype=torch.float64)
    g = batch_graph(torch.tensor([[0, 1, 2, 2, 4], [1, 0, 0, 1, 3]]), 4, 5, self_loops=True)
    assert torch.allclose(dense_adjacency(g, torch.float64) @ values, sum_aggregate(values, g), atol=1e-12)
