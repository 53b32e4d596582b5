"""Kuramoto oscillators: closed-form oracles, reference graphs, per-trajectory graphs, errors on the circle."""

import math

import pytest
import torch

from mpsim.metrics import rollout_metrics
from mpsim.systems.kuramoto import Kuramoto


def test_without_coupling_every_phase_rotates_at_omega():
    system = Kuramoto(coupling=0.0)
    traj = system.generate(4, seed=0)
    expected = traj.x[:, :1] + system.omega * traj.t[None, :, None, None]
    assert torch.allclose(traj.x, expected, atol=1e-8)


def test_mean_phase_rotates_at_omega_on_any_undirected_graph():
    # the coupling is antisymmetric along each undirected edge, so Σ_i θ̇_i = N ω exactly
    system = Kuramoto(graph="barabasi_albert", n_graphs=3, graph_seed=0)
    traj = system.generate(3, seed=2)
    mean = traj.x.mean(dim=2)  # [B, T, D]
    assert torch.allclose(mean, mean[:, :1] + system.omega * traj.t[None, :, None], atol=1e-7)


def test_two_coupled_oscillators_lock_in_closed_form():
    # φ = θ2 − θ1 obeys φ̇ = −2K sin φ, so tan(φ/2) = tan(φ0/2)·e^{−2Kt}
    system = Kuramoto(n_nodes=2, dim=1, graph="erdos_renyi", graph_params={"p": 1.0})
    x0 = torch.tensor([[[-0.4], [0.9]]], dtype=torch.float64)
    t = torch.linspace(0, 3, 31, dtype=torch.float64)
    phi = system.simulate(x0, t).x[0, :, 1, 0] - system.simulate(x0, t).x[0, :, 0, 0]
    expected = 2 * torch.atan(math.tan(1.3 / 2) * torch.exp(-2 * system.coupling * t))
    assert torch.allclose(phi, expected, atol=1e-8)


def test_reference_graphs_and_the_er_edge_count_convention():
    assert Kuramoto(graph="barabasi_albert").params()["n_edges"] == [2 * 25]  # BA(10, 5)
    assert Kuramoto(graph="watts_strogatz").params()["n_edges"] == [2 * 20]  # WS(10, 5, 0.5)
    assert Kuramoto(graph="erdos_renyi").params()["n_edges"] == [2 * 5]  # G(10, m = 5 edges), LightGraphs' Int
    gnp = Kuramoto(graph="erdos_renyi", graph_params={"p": 0.5}, n_graphs=10).params()["n_edges"]
    assert sum(gnp) / 10 / 2 > 15  # G(n, p = 0.5): 22.5 edges expected


def test_isolated_oscillators_rotate_freely():
    system = Kuramoto(graph="erdos_renyi")  # 5 edges on 10 nodes: some nodes are isolated
    isolated = system.adjacency[0].sum(1) == 0
    assert isolated.any()
    traj = system.generate(2, seed=0)
    free = traj.x[:, :1, isolated] + system.omega * traj.t[None, :, None, None]
    assert torch.allclose(traj.x[:, :, isolated], free, atol=1e-8)


def test_natural_frequencies_are_shared_by_the_graph_families():
    omegas = [Kuramoto(graph=g).omega for g in ("barabasi_albert", "erdos_renyi", "watts_strogatz")]
    assert torch.equal(omegas[0], omegas[1]) and torch.equal(omegas[0], omegas[2])
    assert not torch.equal(omegas[0], Kuramoto(omega_seed=1).omega)


def test_per_trajectory_graphs_equal_separate_single_graph_runs():
    multi = Kuramoto(graph="watts_strogatz", graph_seed=1, n_graphs=2)
    traj = multi.generate(4, seed=0, horizon=20)
    for b in range(4):
        single = Kuramoto(graph="watts_strogatz", graph_seed=1 + b % 2)
        alone = single.simulate(traj.x[b : b + 1, 0], traj.t)
        assert torch.allclose(alone.x[0], traj.x[b], atol=1e-7)


def test_errors_are_measured_on_the_circle():
    traj = Kuramoto().generate(3, seed=0, horizon=10)
    assert traj.meta["periods"] == pytest.approx([2 * math.pi] * 3)
    shifted = traj.x + 2 * math.pi * torch.randint(-2, 3, traj.x.shape).double()  # whole turns
    std = torch.ones(3, dtype=torch.float64)
    assert rollout_metrics(shifted, traj.x, std, traj.t, periods=traj.meta["periods"])["rmse"] < 1e-9
    assert rollout_metrics(shifted, traj.x, std, traj.t)["rmse"] > 1.0  # without periods they would count


def test_state_names_and_shapes():
    traj = Kuramoto().generate(2, seed=0)
    assert traj.x.shape == (2, 51, 10, 3) and traj.state_names == ["theta1", "theta2", "theta3"]
    assert Kuramoto(dim=2).state_dim == 2
