"""Monolithic NODE baseline: shapes, sizing from the data, and refusing another node count."""

import pytest
import torch

from mpsim.data.trajectories import Inputs
from mpsim.errors import IncompatibleError
from mpsim.graphs.topology import chain, complete
from mpsim.models.node import NODE


def test_reference_size_and_rollout_shape():
    model = NODE(3, n_nodes=10)
    # ndeln4: Dense(30→32)+LN, Dense(32→32)+LN, Dense(32→30)
    assert sum(p.numel() for p in model.parameters()) == (30 * 32 + 32) + 64 + (32 * 32 + 32) + 64 + (32 * 30 + 30)
    x0 = torch.randn(4, 10, 3)
    out = model.rollout(x0, torch.linspace(0, 1, 6), Inputs(complete(10)))
    assert out.shape == (4, 6, 10, 3) and torch.allclose(out[:, 0], x0, atol=1e-6)


def test_the_compatibility_check_sizes_an_unbuilt_network():
    model = NODE(2)
    assert model.net is None
    model.check_compatible(2, 0, n_nodes=5)
    assert model.n_nodes == 5 and model.net[0].in_features == 10


def test_refuses_another_node_count_clearly():
    model = NODE(2, n_nodes=5)
    with pytest.raises(IncompatibleError, match="flattened state of 5 nodes.*7 nodes.*model=mpnode"):
        model.rollout(torch.randn(1, 7, 2), torch.linspace(0, 1, 3), Inputs(chain(7)))
    # a checkpoint trained on 5 nodes is refused on 7 before any weights are loaded
    fresh = NODE(2)
    with pytest.raises(IncompatibleError, match="cannot run on a graph of 7 nodes"):
        fresh.check_compatible(2, 0, n_nodes=7, trained_nodes=5)
    assert NODE.transfers_across_graphs is False


def test_it_ignores_the_graph_and_sees_every_node():
    torch.manual_seed(0)
    model = NODE(1, n_nodes=3, layer_norm=False).double()
    x0 = torch.randn(1, 3, 1, dtype=torch.float64)
    t = torch.linspace(0, 1, 4, dtype=torch.float64)
    assert torch.allclose(
        model.rollout(x0, t, Inputs(chain(3))), model.rollout(x0, t, Inputs(torch.zeros(2, 0, dtype=torch.long)))
    )
    x1 = x0.clone()
    x1[0, 2, 0] += 1.0  # node 2 is not adjacent to node 0 in any graph here, yet it changes node 0
    assert not torch.allclose(
        model.rollout(x0, t, Inputs(chain(3)))[0, -1, 0], model.rollout(x1, t, Inputs(chain(3)))[0, -1, 0]
    )


def test_controls_are_flattened_with_the_states():
    model = NODE(2, control_dim=1, n_nodes=3)
    assert model.net[0].in_features == 3 * (2 + 1)
    u = torch.zeros(2, 4, 3, 1)
    assert model.rollout(torch.randn(2, 3, 2), torch.linspace(0, 1, 4), Inputs(chain(3), u=u)).shape == (2, 4, 3, 2)
