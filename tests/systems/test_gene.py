"""Gene regulatory dynamics: closed-form and known-answer oracles, hot-spot states, per-trajectory graphs."""

import math

import networkx as nx
import pytest
import torch

from mpsim.errors import ConfigError
from mpsim.systems.gene import GeneRegulation, hotspot_states


def test_empty_graph_decays_exactly_as_exp_minus_t():
    # no edges: ẋ = −x, so x(t) = x0 e^{−t} (the only fixed point, 0, attracts at rate 1)
    system = GeneRegulation(n_nodes=16, graph="erdos_renyi", graph_params={"p": 0.0}, n_graphs=1)
    traj = system.generate(3, seed=0)
    expected = traj.x[:, :1] * torch.exp(-traj.t)[None, :, None, None]
    assert torch.allclose(traj.x, expected, rtol=1e-6, atol=1e-7)


def test_right_hand_side_matches_the_michaelis_menten_sum():
    system = GeneRegulation(n_nodes=16, graph="barabasi_albert", n_graphs=1, graph_seed=7)
    x = 5 * torch.rand(2, 16, 1, dtype=torch.float64)
    g = nx.barabasi_albert_graph(16, 8, seed=7)
    a = torch.tensor(nx.to_numpy_array(g, nodelist=range(16)), dtype=torch.float64)  # symmetric
    expected = -x[..., 0] + (x[..., 0] ** 2 / (1 + x[..., 0] ** 2)) @ a.T
    assert torch.allclose(system.rhs(torch.tensor(0.0), x)[..., 0], expected)


@pytest.mark.parametrize(
    "graph,n,edges",
    [("barabasi_albert", 16, 8 * 8), ("watts_strogatz", 16, 16 * 4), ("barabasi_albert", 64, 32 * 32)],
)
def test_reference_graph_parameters(graph, n, edges):
    # BA(n, n/2) has (n/2)(n − n/2) edges; WS(n, n/2) keeps n·n/4 edges after rewiring (undirected)
    system = GeneRegulation(n_nodes=n, graph=graph, n_graphs=2)
    assert system.params()["n_edges"] == [2 * edges, 2 * edges]  # both directions listed
    assert system.graph_params == ({"k": n // 2} if graph == "barabasi_albert" else {"k": n // 2, "p": 0.5})


def test_erdos_renyi_is_gnp_with_half_the_pairs_on_average():
    system = GeneRegulation(n_nodes=16, graph="erdos_renyi", n_graphs=20)
    mean_edges = sum(system.params()["n_edges"]) / 20 / 2
    assert abs(mean_edges - 0.5 * 16 * 15 / 2) < 8  # G(n, p = 0.5): 60 edges expected, sd ≈ 5.5 / √20


def test_per_trajectory_graphs_equal_separate_single_graph_runs():
    multi = GeneRegulation(n_nodes=16, graph="watts_strogatz", graph_seed=3, n_graphs=3, initial="uniform")
    traj = multi.generate(5, seed=1, horizon=10)
    assert traj.edge_index.shape[:2] == (5, 2)
    for b in range(5):
        single = GeneRegulation(n_nodes=16, graph="watts_strogatz", graph_seed=3 + b % 3, n_graphs=1)
        alone = single.simulate(traj.x[b : b + 1, 0], traj.t)
        assert torch.allclose(alone.x[0], traj.x[b], rtol=1e-6, atol=1e-6)
        kept = traj.edge_index[b][:, traj.edge_index[b][0] >= 0]
        assert torch.equal(kept, single.edge_index)


def test_hotspot_states_fill_rectangles_column_major():
    x = hotspot_states(200, 4, torch.Generator().manual_seed(0))
    assert x.shape == (200, 16)
    hot = x[x > 0]
    assert hot.min() >= 30 and hot.max() <= 50
    assert (x > 0).any(dim=1).all()  # every state has at least one hot cell
    assert ((x > 0).sum(dim=1) < 16).any()  # and usually cold cells
    one = hotspot_states(50, 8, torch.Generator().manual_seed(1), n_spots=1)
    for row in one:  # a single spot is one axis-aligned rectangle on the column-major grid
        grid = row.reshape(8, 8).T  # [row, col]: node k sits at (k mod 8, k div 8)
        rows, cols = torch.nonzero(grid, as_tuple=True)
        assert len(rows) == (rows.max() - rows.min() + 1) * (cols.max() - cols.min() + 1)
        assert len(torch.unique(grid[grid > 0])) == 1


def test_hotspot_needs_a_square_node_count():
    with pytest.raises(ConfigError, match="not a square"):
        GeneRegulation(n_nodes=15)
    GeneRegulation(n_nodes=15, initial="uniform")


def test_data_and_metadata():
    traj = GeneRegulation(n_nodes=16).generate(6, seed=0)
    assert traj.x.shape == (6, 51, 16, 1) and traj.meta["dt"] == pytest.approx(0.05)
    assert (traj.x >= 0).all() and math.isclose(float(traj.t[-1]), 2.5)
    assert traj.meta["params"]["graph_seeds"] == [1, 2, 3, 4, 5]
    assert torch.equal(traj.edge_index[5], traj.edge_index[0])  # trajectory 5 runs on graph 5 mod 5 = 0


def test_mean_field_equals_the_graph_on_a_regular_graph_from_equal_states():
    # a k-regular graph (WS with no rewiring is a ring lattice) from equal node states: every node's input is
    # k·H(x) both ways, so the mean field reproduces the graph's trajectory exactly; on BA (hubs) it does not
    kw = dict(n_nodes=16, graph="watts_strogatz", graph_params={"k": 4, "p": 0.0}, n_graphs=1)
    graph, field = GeneRegulation(**kw), GeneRegulation(**kw, coupling="mean_field")
    x0 = torch.linspace(1.0, 40.0, 3, dtype=torch.float64)[:, None, None].expand(3, 16, 1)  # [B, N, 1] equal nodes
    t = torch.linspace(0.0, 2.0, 21, dtype=torch.float64)
    assert torch.allclose(field.simulate(x0, t).x, graph.simulate(x0, t).x, rtol=1e-7, atol=1e-8)
    ba = dict(n_nodes=16, graph="barabasi_albert", n_graphs=2)
    hot = GeneRegulation(**ba).sample_initial_states(3, torch.Generator().manual_seed(0))
    gap = GeneRegulation(**ba, coupling="mean_field").simulate(hot, t).x - GeneRegulation(**ba).simulate(hot, t).x
    assert gap.abs().max() > 1.0


@pytest.mark.parametrize("mean_degree", [None, 5.0])
def test_mean_field_input_is_k_bar_times_the_mean_activation(mean_degree):
    system = GeneRegulation(n_nodes=16, graph="erdos_renyi", n_graphs=3, coupling="mean_field", mean_degree=mean_degree)
    drawn = GeneRegulation(n_nodes=16, graph="erdos_renyi", n_graphs=3).adjacency  # [G, N, N] the same graphs
    k = drawn.sum(dim=(1, 2)) / 16 if mean_degree is None else torch.full((3,), mean_degree, dtype=torch.float64)
    x = 5 * torch.rand(3, 16, 1, dtype=torch.float64)
    act = x**2 / (1 + x**2)  # [B, N, 1]
    expected = -x + k[:, None, None] * act.mean(dim=1, keepdim=True)
    assert torch.allclose(system.rhs(torch.tensor(0.0), x), expected)
    assert system.params()["coupling"] == "mean_field" and system.params()["mean_degree"] == pytest.approx(k.tolist())
    assert GeneRegulation(n_nodes=16, n_graphs=1).params()["mean_degree"] is None


@pytest.mark.parametrize("kw,match", [({"coupling": "mean"}, "system.coupling"), ({"mean_degree": 0.0}, "mean_degree")])
def test_bad_coupling_settings_are_config_errors(kw, match):
    with pytest.raises(ConfigError, match=match):
        GeneRegulation(n_nodes=16, n_graphs=1, **kw)
