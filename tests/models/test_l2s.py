"""L2S baseline: reference size, shapes, permutation equivariance, ψ, per-trajectory graphs, controls."""

import torch

from mpsim.data.trajectories import Inputs
from mpsim.graphs.topology import chain, complete
from mpsim.models.l2s import L2S
from mpsim.solvers import ODESolver


def _model(d=2, c=0, **kw):
    torch.manual_seed(0)
    return L2S(d, c, solver=ODESolver("dopri5", rtol=1e-7, atol=1e-7), **kw).double()


def test_reference_parameter_count():
    # gnnsc_de0 with H = 32, f = 3: lift 128 + message 1056 + update 1056 + readout 99 + ψ 32
    assert sum(p.numel() for p in L2S(3).parameters()) == 2371


def test_rollout_shape_and_start():
    model = _model()
    x0 = torch.randn(3, 4, 2, dtype=torch.float64)
    t = torch.linspace(0, 1, 6, dtype=torch.float64)
    out = model.rollout(x0, t, Inputs(chain(4)))
    assert out.shape == (3, 6, 4, 2) and torch.allclose(out[:, 0], x0)


def test_permutation_equivariance():
    model = _model()
    n = 5
    ei = chain(n)
    x0 = torch.randn(2, n, 2, dtype=torch.float64)
    t = torch.linspace(0, 1, 5, dtype=torch.float64)
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(3))
    inverse = torch.argsort(perm)
    out = model.rollout(x0, t, Inputs(ei))
    out_perm = model.rollout(x0[:, perm], t, Inputs(inverse[ei]))
    assert torch.allclose(out_perm, out[:, :, perm], atol=1e-6)


def test_sum_aggregation_depends_on_the_number_of_neighbours():
    # unlike MP-NODE's mean, a node with more identical neighbours receives a larger input
    model = _model(d=1)
    x0 = torch.ones(1, 4, 1, dtype=torch.float64)
    t = torch.tensor([0.0, 0.5], dtype=torch.float64)
    star = torch.tensor([[1, 2, 3], [0, 0, 0]])  # node 0 hears three nodes
    single = torch.tensor([[1], [0]])  # node 0 hears one
    assert not torch.allclose(
        model.rollout(x0, t, Inputs(star))[:, 1, 0], model.rollout(x0, t, Inputs(single))[:, 1, 0]
    )


def test_empty_neighbourhood_uses_the_trainable_psi():
    model = _model()
    x0 = torch.randn(2, 3, 2, dtype=torch.float64)
    t = torch.tensor([0.0, 0.3], dtype=torch.float64)
    lonely = torch.zeros(2, 0, dtype=torch.long)
    model.rollout(x0, t, Inputs(lonely)).sum().backward()
    assert model.processor[0].psi.grad is not None and model.processor[0].psi.grad.abs().sum() > 0
    with torch.no_grad():
        before = model.rollout(x0, t, Inputs(lonely))
        model.processor[0].psi.fill_(1.0)
        assert not torch.allclose(model.rollout(x0, t, Inputs(lonely)), before)


def test_per_trajectory_graphs_equal_separate_runs():
    model = _model()
    x0 = torch.randn(2, 4, 2, dtype=torch.float64)
    t = torch.linspace(0, 1, 4, dtype=torch.float64)
    a, b = chain(4), complete(4)
    padded = torch.full((2, 2, b.shape[1]), -1)
    padded[0, :, : a.shape[1]], padded[1] = a, b
    both = model.rollout(x0, t, Inputs(padded))
    assert torch.allclose(both[0], model.rollout(x0[:1], t, Inputs(a))[0], atol=1e-7)
    assert torch.allclose(both[1], model.rollout(x0[1:], t, Inputs(b))[0], atol=1e-7)


def test_controls_enter_with_zero_order_hold():
    model = _model(d=2, c=1)
    x0 = torch.randn(1, 3, 2, dtype=torch.float64)
    t = torch.linspace(0, 1, 5, dtype=torch.float64)
    u = torch.zeros(1, 5, 3, 1, dtype=torch.float64)
    base = model.rollout(x0, t, Inputs(chain(3), u=u))
    u_late = u.clone()
    u_late[:, 3:] = 1.0  # changes from t[3] on: the first three steps are unaffected
    late = model.rollout(x0, t, Inputs(chain(3), u=u_late))
    assert torch.equal(base[:, :4], late[:, :4]) and not torch.allclose(base[:, 4], late[:, 4])


def test_dense_and_edge_list_aggregation_agree():
    # small graphs aggregate with a dense adjacency product, large ones over the edge list: same field
    dense, sparse = _model(), _model(dense_max_nodes=0)
    x0 = torch.randn(2, 5, 2, dtype=torch.float64)
    t = torch.linspace(0, 1, 4, dtype=torch.float64)
    a, b = chain(5), complete(5)
    padded = torch.full((2, 2, b.shape[1]), -1)
    padded[0, :, : a.shape[1]], padded[1] = a, b
    for graph in (a, padded):
        assert torch.allclose(dense.rollout(x0, t, Inputs(graph)), sparse.rollout(x0, t, Inputs(graph)), atol=1e-10)
    loops_dense, loops_sparse = _model(self_loops=True), _model(self_loops=True, dense_max_nodes=0)
    assert torch.allclose(loops_dense.rollout(x0, t, Inputs(a)), loops_sparse.rollout(x0, t, Inputs(a)), atol=1e-10)


def test_full_graph_sums_over_every_node_whatever_the_datas_graph():
    # graph="full" (MPNODE.jl's shipped configs): the sum runs over all nodes, self included, so the data's graph
    # does not matter and the model equals the data-graph model on the complete graph with self-loops
    t = torch.linspace(0, 1, 6, dtype=torch.float64)
    x0 = torch.randn(2, 4, 2, dtype=torch.float64)
    full, data = _model(graph="full"), _model(self_loops=True)
    data.load_state_dict(full.state_dict())
    on_chain = full.rollout(x0, t, Inputs(chain(4)))
    assert torch.allclose(on_chain, full.rollout(x0, t, Inputs(torch.tensor([[0, 2], [2, 0]]))), atol=1e-12)
    assert torch.allclose(on_chain, data.rollout(x0, t, Inputs(complete(4, self_loops=True))), atol=1e-10)
    assert not torch.allclose(data.rollout(x0, t, Inputs(chain(4))), on_chain, atol=1e-4)
