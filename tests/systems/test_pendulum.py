import math

import pytest
import torch

from mpsim.errors import ConfigError
from mpsim.systems import CoupledPendulums


def test_energy_is_conserved_along_long_trajectories():
    system = CoupledPendulums(n_nodes=5, graph="chain")
    traj = system.generate(6, seed=1, dt=0.05, horizon=400)  # 20 s, large angles up to ±π/2
    energy = system.energy(traj.x)  # [B, T]
    drift = ((energy - energy[:, :1]).abs() / energy[:, :1].abs()).max()
    assert drift < 1e-6


def test_spring_forces_change_the_energy_if_the_equations_were_wrong():
    # the oracle can fail: removing the cos θ factor from the spring torque breaks conservation
    system = CoupledPendulums(n_nodes=2)
    traj = system.generate(4, seed=2, dt=0.05, horizon=200)
    energy = system.energy(traj.x)
    assert (energy.std(dim=1) / energy.mean(dim=1).abs()).max() < 1e-6
    wrong = CoupledPendulums(n_nodes=2)
    wrong._spring_sum = lambda s: torch.zeros_like(s)  # springs ignored by the dynamics but not by the energy
    traj_w = wrong.generate(4, seed=2, dt=0.05, horizon=200)
    e_w = wrong.energy(traj_w.x)
    assert (e_w.std(dim=1) / e_w.mean(dim=1).abs()).max() > 1e-3


def test_small_angle_normal_modes():
    # two pendulums: in-phase mode ω² = g/l, anti-phase mode ω² = g/l + 2k/m
    system = CoupledPendulums(n_nodes=2, mass=1.0, length=1.5, spring=2.0, gravity=9.81)
    eps = 1e-4
    x0 = torch.tensor([[[eps, 0.0], [-eps, 0.0]]], dtype=torch.float64)  # anti-phase
    w2 = 9.81 / 1.5 + 2 * 2.0 / 1.0
    period = 2 * math.pi / math.sqrt(w2)
    t = torch.linspace(0, period, 201, dtype=torch.float64)
    traj = system.simulate(x0, t)
    assert torch.allclose(traj.x[0, -1], x0[0], atol=1e-9)
    assert traj.x[0, 100, 0, 0] == pytest.approx(-eps, rel=1e-4)


def test_regular_at_horizontal_angles():
    system = CoupledPendulums(n_nodes=3, graph="ring")
    x = torch.tensor([[[math.pi / 2, 0.0], [-math.pi / 2, 1.0], [0.3, -1.0]]], dtype=torch.float64)
    assert torch.isfinite(system.rhs(torch.tensor(0.0), x)).all()


def test_unknown_graph_kind_is_a_clear_error():
    with pytest.raises(ConfigError, match="unknown graph kind 'not-a-graph'"):
        CoupledPendulums(n_nodes=3, graph="not-a-graph")


def test_generate_is_reproducible_and_shaped():
    system = CoupledPendulums()
    a, b = system.generate(3, seed=5), system.generate(3, seed=5)
    assert a.x.shape == (3, system.horizon + 1, 2, 2)
    assert torch.equal(a.x, b.x)
    assert not torch.equal(a.x, system.generate(3, seed=6).x)
    assert a.meta["system"] == "pendulum2" and a.meta["state_names"] == ["theta", "omega"]
