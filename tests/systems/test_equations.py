"""`system=equations`: built-in systems restated as specs give the same trajectories (float64, 1e-10), and the
shipped example specs simulate."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from mpsim.effects import LinearDamping
from mpsim.equations import load_spec_file
from mpsim.errors import ConfigError
from mpsim.systems.equations import EquationsSystem
from mpsim.systems.kuramoto import Kuramoto
from mpsim.systems.lorenz import CoupledLorenz
from mpsim.systems.pendulum import CoupledPendulums

EXAMPLES = Path(__file__).resolve().parents[2] / "examples" / "equations"


def _same_trajectories(builtin, twin, t):
    x0 = builtin.sample_initial_states(6, torch.Generator().manual_seed(3))
    a = builtin.simulate(x0, t, rtol=1e-10, atol=1e-12)
    b = twin.simulate(x0, t, rtol=1e-10, atol=1e-12)
    assert a.x.shape == b.x.shape
    return float((a.x - b.x).abs().max())


def test_pendulums_twin():
    builtin = CoupledPendulums(n_nodes=4, graph="ring", mass=1.3, length=1.1, spring=2.5, gravity=9.7)
    twin = EquationsSystem({
        "states": ["theta", "omega"],
        "equations": {"theta": "omega",
                      "omega": "-(g/l)*sin(theta) - (k/m)*cos(theta)*sum_nbr(sin(theta) - sin(theta_j))"},
        "params": {"g": 9.7, "l": 1.1, "k": 2.5, "m": 1.3}, "nodes": 4, "graph": "ring"})
    assert _same_trajectories(builtin, twin, torch.linspace(0, 5, 51, dtype=torch.float64)) < 1e-10


def test_lorenz_twin_with_a_given_coupling_matrix():
    builtin = CoupledLorenz(n_nodes=3, coupling=1.0)
    twin = EquationsSystem({
        "states": ["x", "y", "z"],
        "equations": {"x": "sigma*(y - x) + lin(H)", "y": "x*(rho - z) - y + lin(H)", "z": "x*y - beta*z + lin(H)"},
        "params": {"sigma": 10.0, "rho": 28.0, "beta": 8.0 / 3.0, "H": builtin.H.tolist()}})
    assert twin.n_nodes == 3
    assert _same_trajectories(builtin, twin, torch.linspace(0, 2.5, 51, dtype=torch.float64)) < 1e-10


def test_kuramoto_twin_on_the_same_graph():
    builtin = Kuramoto(n_nodes=10, dim=3)
    w = builtin.omega.tolist()
    twin = EquationsSystem({
        "states": ["theta1", "theta2", "theta3"],
        "equations": {f"theta{c}": f"w{c} + K*sum_nbr(sin(theta{c}_j - theta{c}))" for c in (1, 2, 3)},
        "params": {"w1": w[0], "w2": w[1], "w3": w[2], "K": 1.0 / 3.0},
        "edges": builtin.edge_index.T.tolist(), "directed": True, "nodes": 10})
    assert torch.equal(twin.edge_index, builtin.edge_index)
    assert _same_trajectories(builtin, twin, torch.linspace(0, 2.5, 51, dtype=torch.float64)) < 1e-10


def test_effects_and_graph_options():
    spec = {"states": ["x", "v"], "equations": {"x": "v", "v": "-x"}, "nodes": 2, "init": {"x": [1.0, 1.0], "v": [0, 0]}}
    damped = EquationsSystem(spec, effects=[LinearDamping(0.5, target="v")]).generate(1, 0, dt=0.1, horizon=100)
    free = EquationsSystem(spec).generate(1, 0, dt=0.1, horizon=100)
    assert free.x[0, -1, 0, 0].abs() > 0.5 > damped.x[0, -1, 0, 0].abs()  # cos(10) = -0.84; damped ≈ e^{-2.5}
    undirected = EquationsSystem({**spec, "edges": [[0, 1]]})
    assert undirected.edge_index.tolist() == [[0, 1], [1, 0]]
    with pytest.raises(ConfigError, match="nodes is unknown|number of nodes is unknown"):
        EquationsSystem({"states": ["x"], "equations": {"x": "sum_nbr(x_j - x)"}})
    with pytest.raises(ConfigError, match="no graph"):
        EquationsSystem({"states": ["x"], "equations": {"x": "sum_nbr(x_j - x)"}, "nodes": 3})
    with pytest.raises(ConfigError, match="names node 5"):
        EquationsSystem({"states": ["x"], "equations": {"x": "-x"}, "nodes": 3, "edges": [[0, 5]]})
    with pytest.raises(ConfigError, match="system.init.q"):
        EquationsSystem({**spec, "init": {"q": [0, 1]}})
    with pytest.raises(ConfigError, match="node counts disagree"):
        EquationsSystem({"states": ["x"], "equations": {"x": "-a*x"}, "params": {"a": [1.0, 2.0]}, "nodes": 3})


@pytest.mark.parametrize("name", sorted(p.stem for p in EXAMPLES.glob("*.yaml")))
def test_example_specs_simulate(name):
    system = EquationsSystem(load_spec_file(EXAMPLES / f"{name}.yaml"))
    data = system.generate(2, seed=0, horizon=5)
    assert system.name == name and data.meta["system"] == name
    assert torch.isfinite(data.x).all() and data.x.shape[2] == system.n_nodes


def test_examples_cover_what_the_issue_lists():
    assert {p.stem for p in EXAMPLES.glob("*.yaml")} >= {
        "pendulum_inertia", "pendulums_linear_spring", "pendulums_bob_spring", "kuramoto_frequencies",
        "lorenz_network", "fitzhugh_nagumo"}
