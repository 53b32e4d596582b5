import pytest
import torch

from mpsim.data.trajectories import Inputs
from mpsim.graphs.topology import chain, complete
from mpsim.models import MPNODE
from mpsim.solvers import ODESolver


def _model(d=2, **kw):
    torch.manual_seed(0)
    return MPNODE(d, solver=ODESolver("dopri5", rtol=1e-7, atol=1e-7), **kw).double()


def test_reference_parameter_count_for_lorenz():
    # MPNODE.jl: Dense(6→32, tanh) → Dense(32→32, tanh) → Dense(32→6) = 1478 parameters
    assert sum(p.numel() for p in MPNODE(3).parameters()) == 1478


def test_rollout_starts_at_x0_and_has_batch_first_shape():
    model = _model()
    x0 = torch.randn(3, 4, 2, dtype=torch.float64)
    t = torch.linspace(0, 1, 6, dtype=torch.float64)
    pred, aux = model.rollout_aux(x0, t, Inputs(chain(4)))
    assert pred.shape == (3, 6, 4, 2) and aux["messages"].shape == (3, 6, 4, 3)
    assert torch.allclose(pred[:, 0], x0)
    assert torch.all(aux["messages"][:, 0] == 0)  # messages start at zero


def test_permutation_equivariance():
    # relabelling the nodes (and the graph accordingly) permutes the prediction the same way
    model = _model()
    n = 5
    ei = chain(n)  # not symmetric under relabelling, so the test is not trivially satisfied
    x0 = torch.randn(2, n, 2, dtype=torch.float64)
    t = torch.linspace(0, 2, 9, dtype=torch.float64)
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(3))
    inverse = torch.argsort(perm)
    out = model.rollout(x0, t, Inputs(ei))
    out_perm = model.rollout(x0[:, perm], t, Inputs(inverse[ei]))
    assert torch.allclose(out_perm, out[:, :, perm], atol=1e-6)
    # sanity: with the graph NOT relabelled the outputs differ, so the check can fail
    assert not torch.allclose(model.rollout(x0[:, perm], t, Inputs(ei)), out[:, :, perm], atol=1e-4)


def test_messages_couple_nodes_and_zero_messages_decouple_them():
    model = _model()
    t = torch.linspace(0, 2, 11, dtype=torch.float64)
    x0 = torch.randn(1, 3, 2, dtype=torch.float64)
    x0b = x0.clone()
    x0b[0, 2] += 0.5  # change only node 2
    ei = complete(3)
    a, b = model.rollout(x0, t, Inputs(ei)), model.rollout(x0b, t, Inputs(ei))
    assert (a[0, -1, 0] - b[0, -1, 0]).abs().max() > 1e-6  # node 0 feels node 2 through messages
    model.zero_messages = True
    a, b = model.rollout(x0, t, Inputs(ei)), model.rollout(x0b, t, Inputs(ei))
    assert torch.allclose(a[0, :, :2], b[0, :, :2])  # without messages nodes evolve independently


def test_same_weights_run_on_any_graph_size():
    model = _model(d=3)
    t = torch.linspace(0, 1, 4, dtype=torch.float64)
    for n in (1, 3, 10):
        assert model.rollout(torch.randn(2, n, 3, dtype=torch.float64), t, Inputs(complete(n))).shape == (2, 4, n, 3)


def test_per_trajectory_graphs_equal_separate_rollouts():
    model = _model()
    t = torch.linspace(0, 1, 5, dtype=torch.float64)
    x0 = torch.randn(2, 3, 2, dtype=torch.float64)
    g0, g1 = chain(3), complete(3)
    padded = torch.full((2, 2, g1.shape[1]), -1, dtype=torch.long)
    padded[0, :, : g0.shape[1]], padded[1] = g0, g1
    both = model.rollout(x0, t, Inputs(padded))
    assert torch.allclose(both[:1], model.rollout(x0[:1], t, Inputs(g0)), atol=1e-6)
    assert torch.allclose(both[1:], model.rollout(x0[1:], t, Inputs(g1)), atol=1e-6)


def test_normalisation_round_trip():
    model = _model()
    model.set_normalisation(torch.tensor([1.0, -2.0]), torch.tensor([2.0, 0.5]))
    x = torch.randn(4, 2, dtype=torch.float64)
    assert torch.allclose(model.denormalise(model.normalise(x)), x)


def test_bad_sizes_are_refused():
    with pytest.raises(ValueError, match="message_size"):
        MPNODE(2, message_size=-1)


def test_sum_aggregation_sees_the_degree_and_mean_does_not():
    t = torch.linspace(0, 1, 6, dtype=torch.float64)
    mean, total = _model(), _model(aggregation="sum")
    total.load_state_dict(mean.state_dict())
    x0 = torch.randn(2, 4, 2, dtype=torch.float64)
    pairs = torch.tensor([[0, 1, 2, 3], [1, 0, 3, 2]])  # every node has one neighbour: sum = mean
    assert torch.allclose(mean.rollout(x0, t, Inputs(pairs)), total.rollout(x0, t, Inputs(pairs)), atol=1e-10)
    ring = complete(4)  # three neighbours each: the sum is three times the mean
    assert not torch.allclose(mean.rollout(x0, t, Inputs(ring)), total.rollout(x0, t, Inputs(ring)), atol=1e-4)
    with pytest.raises(ValueError, match="aggregation"):
        MPNODE(2, aggregation="max")


@pytest.mark.parametrize("kw", [{}, {"aggregation": "sum"}, {"self_loops": True}, {"graph": "full"}])
def test_dense_and_edge_list_aggregation_agree(kw):
    # graphs of at most dense_max_nodes nodes aggregate with a dense adjacency product, larger ones over the edge
    # list: the same rollouts and one-step predictions, with shared and per-trajectory graphs, and isolated nodes
    # (nodes 2..4 of the first graph have no neighbours: their mean message is 0)
    dense, sparse = _model(**kw), _model(dense_max_nodes=0, **kw)
    x0 = torch.randn(2, 5, 2, dtype=torch.float64)
    t = torch.linspace(0, 1, 4, dtype=torch.float64)
    pair, ring = torch.tensor([[0, 1], [1, 0]]), complete(5)
    padded = torch.full((2, 2, ring.shape[1]), -1)
    padded[0, :, :2], padded[1] = pair, ring
    for graph in (chain(5), pair, padded):
        a, b = dense.rollout(x0, t, Inputs(graph)), sparse.rollout(x0, t, Inputs(graph))
        assert torch.allclose(a, b, atol=1e-10)
        x = torch.cat([a, a + 0.1], dim=0)  # [4, T, N, D]: an observed trajectory for one-step predictions
        g = graph if graph.dim() == 2 else torch.cat([graph, graph])
        assert torch.allclose(dense.one_step(x, t, Inputs(g)), sparse.one_step(x, t, Inputs(g)), atol=1e-10)
    if kw.get("graph") != "full":  # the graph matters (graph=full ignores it by design)
        assert not torch.allclose(dense.rollout(x0, t, Inputs(chain(5))), dense.rollout(x0, t, Inputs(ring)), atol=1e-4)


def test_full_graph_ignores_the_datas_graph_like_mpnode_jl():
    # graph="full" (MPNODE.jl's shipped configs): messages go all-to-all with self-loops whatever graph the data
    # carries, so it equals the data-graph model run on the complete graph with self-loops
    t = torch.linspace(0, 1, 6, dtype=torch.float64)
    x0 = torch.randn(2, 4, 2, dtype=torch.float64)
    full, sys_graph = _model(graph="full"), _model(self_loops=True)
    sys_graph.load_state_dict(full.state_dict())
    on_chain, on_pairs = (
        full.rollout(x0, t, Inputs(chain(4))),
        full.rollout(x0, t, Inputs(torch.tensor([[0, 2], [2, 0]]))),
    )
    assert torch.allclose(on_chain, on_pairs, atol=1e-12)
    assert torch.allclose(on_chain, sys_graph.rollout(x0, t, Inputs(complete(4, self_loops=True))), atol=1e-10)
    # the default follows the data's graph: the same two graphs give different predictions
    assert not torch.allclose(sys_graph.rollout(x0, t, Inputs(chain(4))), on_chain, atol=1e-4)
    with pytest.raises(ValueError, match="model.graph"):
        MPNODE(2, graph="sys")
