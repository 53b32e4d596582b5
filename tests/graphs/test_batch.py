"""The graph a model passes messages on."""

import pytest
import torch

from mpsim.graphs.batch import message_graph


def test_full_message_graph_is_all_to_all_with_self_loops_whatever_the_data_graph():
    data = torch.tensor([[0, 1], [1, 0]])  # one edge each way on 3 nodes
    full = message_graph(data, 2, 3, mode="full")
    pairs = sorted(zip(full.src.tolist(), full.dst.tolist(), strict=True))
    assert pairs == sorted((g * 3 + i, g * 3 + j) for g in range(2) for i in range(3) for j in range(3))
    assert torch.allclose(full.inv_degree, torch.full((6, 1), 1 / 3))
    assert message_graph(data, 2, 3).src.numel() == 4  # "data": the data's own edges in each of the 2 graphs
    with pytest.raises(ValueError, match="model.graph"):
        message_graph(data, 2, 3, mode="sys")
