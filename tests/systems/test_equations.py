"""`system=equations`: built-in systems restated as specs give the same trajectories (float64, 1e-10), and the
shipped example specs simulate."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from mpsim.effects import LinearDamping
from mpsim.errors import ConfigError
from mpsim.spec import load_spec_file
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
    twin = EquationsSystem(
        {
            "states": ["theta", "omega"],
            "equations": {
                "theta": "omega",
                "omega": "-(g/l)*sin(theta) - (k/m)*cos(theta)*sum_nbr(sin(theta) - sin(theta_j))",
            },
            "params": {"g": 9.7, "l": 1.1, "k": 2.5, "m": 1.3},
            "nodes": 4,
            "graph": "ring",
        }
    )
    assert _same_trajectories(builtin, twin, torch.linspace(0, 5, 51, dtype=torch.float64)) < 1e-10


def test_lorenz_twin_with_a_given_coupling_matrix():
    builtin = CoupledLorenz(n_nodes=3, coupling=1.0)
    twin = EquationsSystem(
        {
            "states": ["x", "y", "z"],
            "equations": {"x": "sigma*(y - x) + lin(H)", "y": "x*(rho - z) - y + lin(H)", "z": "x*y - beta*z + lin(H)"},
            "params": {"sigma": 10.0, "rho": 28.0, "beta": 8.0 / 3.0, "H": builtin.H.tolist()},
        }
    )
    assert twin.n_nodes == 3
    assert _same_trajectories(builtin, twin, torch.linspace(0, 2.5, 51, dtype=torch.float64)) < 1e-10


def test_kuramoto_twin_on_the_same_graph():
    builtin = Kuramoto(n_nodes=10, dim=3)
    w = builtin.omega.tolist()
    twin = EquationsSystem(
        {
            "states": ["theta1", "theta2", "theta3"],
            "equations": {f"theta{c}": f"w{c} + K*sum_nbr(sin(theta{c}_j - theta{c}))" for c in (1, 2, 3)},
            "params": {"w1": w[0], "w2": w[1], "w3": w[2], "K": 1.0 / 3.0},
            "edges": builtin.edge_index.T.tolist(),
            "directed": True,
            "nodes": 10,
        }
    )
    assert torch.equal(twin.edge_index, builtin.edge_index)
    assert _same_trajectories(builtin, twin, torch.linspace(0, 2.5, 51, dtype=torch.float64)) < 1e-10


def test_effects_and_graph_options():
    spec = {
        "states": ["x", "v"],
        "equations": {"x": "v", "v": "-x"},
        "nodes": 2,
        "init": {"x": [1.0, 1.0], "v": [0, 0]},
    }
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
        "pendulum_inertia",
        "pendulums_linear_spring",
        "pendulums_bob_spring",
        "kuramoto_frequencies",
        "lorenz_network",
        "fitzhugh_nagumo",
        "lorenz96",
    }


# ---- Lorenz-96 written with shift (issue 72) ------------------------------------------------------------------
def _lorenz96_numpy(x, forcing, boundary=None):  # x: [B, N] -> [B, N]; boundary None: a ring
    if boundary is None:
        nxt, prev, prev2 = np.roll(x, -1, axis=1), np.roll(x, 1, axis=1), np.roll(x, 2, axis=1)
    else:
        padded = np.pad(x, ((0, 0), (2, 1)), constant_values=boundary)
        nxt, prev, prev2 = padded[:, 3:], padded[:, 1:-2], padded[:, :-3]
    return (nxt - prev2) * prev - x + forcing


def test_lorenz96_example_is_written_with_shift_and_matches_numpy():
    spec = load_spec_file(EXAMPLES / "lorenz96.yaml")
    assert "shift(x, 1)" in spec["equations"]["x"] and "lin(" not in spec["equations"]["x"]
    ring = EquationsSystem(spec)
    assert ring.n_nodes == 10 and ring.spec.shift_boundary == "wrap"
    x = ring.sample_initial_states(4, torch.Generator().manual_seed(0))  # [4, 10, 1]
    got = ring.dynamics(torch.tensor(0.0), x)[..., 0].numpy()
    assert np.abs(got - _lorenz96_numpy(x[..., 0].numpy(), 8.0)).max() < 1e-12
    chain = EquationsSystem(spec, graph="chain", shift_boundary=0.0)
    got = chain.dynamics(torch.tensor(0.0), x)[..., 0].numpy()
    assert np.abs(got - _lorenz96_numpy(x[..., 0].numpy(), 8.0, boundary=0.0)).max() < 1e-12
    with pytest.raises(
        ConfigError, match=r"graph is 'chain', not a ring.*or system\.shift_boundary=0\.0 on the command line"
    ):
        EquationsSystem(spec, graph="chain")


def test_lorenz96_simulates_from_the_command_layer(cfg_factory, tmp_path):
    from mpsim.commands.simulate import run_simulate

    spec = EXAMPLES / "lorenz96.yaml"
    cfg = cfg_factory("simulate", "system=equations", f"system.spec={spec}", "n=3", "data.horizon=20")
    summary = run_simulate(cfg, output_dir=tmp_path / "sim")
    data = np.load(tmp_path / "sim" / "trajectories.npz")
    x = data["x"]  # [B, T, N, D]
    assert summary["system"] == "lorenz96" and x.shape == (3, 21, 10, 1) and np.isfinite(x).all()
    # the stored trajectory is the numpy field's: classical RK4 at dt/100 from the stored initial states
    t, y, out = data["t"].astype(np.float64), x[:, 0, :, 0].astype(np.float64), [x[:, 0, :, 0]]
    h = (t[1] - t[0]) / 100
    for _ in range(len(t) - 1):  # a loop in time only; each step is vectorised over trajectories and nodes
        for _ in range(100):
            k1 = _lorenz96_numpy(y, 8.0)
            k2 = _lorenz96_numpy(y + h / 2 * k1, 8.0)
            k3 = _lorenz96_numpy(y + h / 2 * k2, 8.0)
            k4 = _lorenz96_numpy(y + h * k3, 8.0)
            y = y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        out.append(y)
    assert np.abs(np.stack(out, axis=1) - x[..., 0]).max() < 1e-5  # measured 4.8e-7 (dopri5 at rtol 1e-8)


OSCILLATOR = {"states": ["x", "v"], "equations": {"x": "v", "v": "-x"}, "nodes": 1}


def test_semi_implicit_euler_is_the_symplectic_euler_map():
    # v first (v1 = v0 - h x0), then x with the new v (x1 = x0 + h v1): one step is [[1 - h², h], [-h, 1]]
    h, every, steps = 0.05, 4, 30
    system = EquationsSystem({**OSCILLATOR, "nodes": 3}, integrator="semi_implicit_euler", substep=h)
    x0 = torch.tensor([[[1.0, 0.0], [0.3, -0.7], [-2.0, 0.5]]], dtype=torch.float64)  # [1, 3, 2]
    t = 0.1 + torch.arange(steps + 1, dtype=torch.float64) * every * h
    data = system.simulate(x0, t)
    step = torch.tensor([[1 - h * h, h], [-h, 1.0]], dtype=torch.float64)
    expected = torch.stack([x0[0] @ torch.linalg.matrix_power(step, every * k).T for k in range(steps + 1)])
    assert data.x.shape == (1, steps + 1, 3, 2)
    assert torch.allclose(data.x[0], expected, atol=1e-12, rtol=0)
    energy = (data.x**2).sum(-1)  # the symplectic map keeps the energy within O(h) of its start: no drift
    assert float((energy - energy[:, :1]).abs().max()) < 2 * h * float(energy[:, 0].max())


def test_semi_implicit_euler_includes_effects_and_uses_the_declared_kinematic_rows():
    h = 0.01
    damped = EquationsSystem(
        OSCILLATOR, integrator="semi_implicit_euler", substep=h, effects=[LinearDamping(0.5, target="v")]
    )
    x0 = torch.tensor([[[1.0, 0.0]]], dtype=torch.float64)
    t = torch.arange(11, dtype=torch.float64) * 0.1
    step = torch.tensor([[1 - h * h, h * (1 - 0.5 * h)], [-h, 1 - 0.5 * h]], dtype=torch.float64)  # v' = -x - 0.5v
    expected = torch.stack([x0[0, 0] @ torch.linalg.matrix_power(step, 10 * k).T for k in range(11)])
    assert torch.allclose(damped.simulate(x0, t).x[0, :, 0], expected, atol=1e-12, rtol=0)
    # nothing kinematic: both rows in the first half step, i.e. explicit Euler [[1, h], [-h, 1]]
    explicit = EquationsSystem({**OSCILLATOR, "kinematic": []}, integrator="semi_implicit_euler", substep=h)
    forward = torch.tensor([[1.0, h], [-h, 1.0]], dtype=torch.float64)
    expected = torch.stack([x0[0, 0] @ torch.linalg.matrix_power(forward, 10 * k).T for k in range(11)])
    assert torch.allclose(explicit.simulate(x0, t).x[0, :, 0], expected, atol=1e-12, rtol=0)


def test_dopri5_stays_the_default_and_generate_uses_the_chosen_integrator():
    spec = {**OSCILLATOR, "init": {"x": [1.0, 1.0], "v": [0.0, 0.0]}, "dt": 0.1, "horizon": 20}
    default = EquationsSystem(spec)
    assert default.integrator == "dopri5" and default.substep is None
    exact = default.generate(1, seed=0)
    assert torch.allclose(exact.x[0, :, 0, 0], torch.cos(exact.t), atol=1e-8)
    euler = EquationsSystem({**spec, "integrator": "semi_implicit_euler", "substep": 0.05}).generate(1, seed=0)
    error = float((euler.x[0, :, 0, 0] - torch.cos(euler.t)).abs().max())
    assert 1e-3 < error < 0.1  # an O(h) artefact, not the exact solution
    assert euler.meta["params"]["spec"]["integrator"] == "semi_implicit_euler"  # part of the cache key


def test_integrator_keys_are_checked():
    with pytest.raises(ConfigError, match="'rk45' is not an integrator.*Choose one of dopri5, semi_implicit_euler"):
        EquationsSystem(OSCILLATOR, integrator="rk45")
    with pytest.raises(ConfigError, match="needs its step: set substep"):
        EquationsSystem(OSCILLATOR, integrator="semi_implicit_euler")
    with pytest.raises(ConfigError, match="system.substep must be a positive number"):
        EquationsSystem(OSCILLATOR, integrator="semi_implicit_euler", substep=-0.1)
    with pytest.raises(ConfigError, match="dopri5 chooses its own steps"):
        EquationsSystem(OSCILLATOR, substep=0.01)
    with pytest.raises(ConfigError, match="system.dt = 0.05 is not a whole multiple of system.substep = 0.003"):
        EquationsSystem({**OSCILLATOR, "dt": 0.05}, integrator="semi_implicit_euler", substep=0.003)
    system = EquationsSystem(OSCILLATOR, integrator="semi_implicit_euler", substep=0.02)
    with pytest.raises(ConfigError, match=r"\(system.dt or data.dt\) = 0.05 is not a whole multiple"):
        system.generate(1, seed=0, dt=0.05, horizon=3)
    from mpsim.effects import DelayedFeedback

    with pytest.raises(ConfigError, match="cannot integrate a DelayedFeedback"):
        EquationsSystem(
            OSCILLATOR,
            integrator="semi_implicit_euler",
            substep=0.01,
            effects=[DelayedFeedback(0.1, delay=0.5, target="v", source="x")],
        )


# ---- a driven twin (issue 60): the spec's inputs driven by system.input, stored in the data ----------------
DRIVEN = {**OSCILLATOR, "inputs": ["u"], "equations": {"x": "v", "v": "-k*x + u"}, "params": {"k": 4.0}}


def _piecewise_exact(data, k=4.0):
    """[B, T, 2] the exact solution of x'' = −k x + u for the data's own u, held as its meta says."""
    w, hold = k**0.5, data.meta["input_hold"]
    t, u, s = data.t, data.u[:, :, 0, 0], data.x[:, 0, 0]
    out = [s]
    for i in range(t.numel() - 1):  # the reference, one interval at a time
        h = float(t[i + 1] - t[i])
        a = u[:, i]
        b = torch.zeros_like(a) if hold == "zoh" else (u[:, i + 1] - a) / h
        ex, ev = s[:, 0] - a / k, s[:, 1] - b / k
        c, sn = math.cos(w * h), math.sin(w * h)
        s = torch.stack([(a + b * h) / k + ex * c + ev / w * sn, b / k - ex * w * sn + ev * c], -1)
        out.append(s)
    return torch.stack(out, 1)


@pytest.mark.parametrize("hold", ["zoh", "linear"])
@pytest.mark.parametrize("kind", ["steps", "prbs", "multisine"])
def test_a_driven_twin_integrates_exactly_the_input_it_stores(kind, hold):
    system = EquationsSystem(DRIVEN, input={"kind": kind, "hold": hold, "seed": 1})
    assert system.control_names == ("u",) and system.control_dim == 1
    data = system.generate(3, seed=2, dt=0.1, horizon=40)
    assert data.u.shape == (3, 41, 1, 1) and data.control_names == ["u"] and data.meta["input_hold"] == hold
    assert torch.allclose(data.x[:, :, 0], _piecewise_exact(data), atol=1e-7)
    again = system.generate(3, seed=2, dt=0.1, horizon=40)
    assert torch.equal(again.u, data.u) and torch.equal(again.x, data.x)  # reproducible
    assert not torch.equal(system.generate(3, seed=3, dt=0.1, horizon=40).u, data.u)  # another split, other draws
    assert not torch.equal(data.u[0], data.u[1])  # one realisation per trajectory


def test_a_driven_twin_with_semi_implicit_euler_and_effects():
    system = EquationsSystem(
        DRIVEN,
        input={"kind": "steps", "levels": [1.0, 2.0], "duration": [0.3, 0.6]},
        integrator="semi_implicit_euler",
        substep=0.01,
        effects=[LinearDamping(0.5, target="v")],
    )
    data = system.generate(2, seed=0, dt=0.1, horizon=20)
    x, u, h = data.x[:, 0, 0], data.u[:, :, 0, 0], 0.01
    for i in range(20):  # symplectic Euler, the interval's sample held over its ten steps
        for _ in range(10):
            v = x[:, 1] + h * (-4.0 * x[:, 0] + u[:, i] - 0.5 * x[:, 1])
            x = torch.stack([x[:, 0] + h * v, v], -1)
        assert torch.allclose(data.x[:, i + 1, 0], x, atol=1e-12)


def test_a_driven_twin_reads_its_input_from_a_file(tmp_path):
    path = tmp_path / "drive.csv"
    t = np.arange(0, 3.001, 0.05)
    pd.DataFrame({"t": t, "torque": np.sin(2 * t), "other": 0.0}).to_csv(path, index=False)
    for hold, index in (("zoh", [0, 0, 1, 1]), ("linear", None)):
        system = EquationsSystem(DRIVEN, input={"file": str(path), "column": "torque", "hold": hold})
        data = system.generate(2, seed=0, dt=0.025, horizon=40)
        u = data.u[:, :, 0, 0]
        assert torch.equal(u[0], u[1])  # the same recorded signal drives every trajectory
        expected = np.sin(2 * t[index]) if index else np.sin(2 * data.t[:4].numpy())
        assert np.allclose(u[0, :4].numpy(), expected, atol=1e-3 if hold == "linear" else 1e-12)
        assert torch.allclose(data.x[:, :, 0], _piecewise_exact(data), atol=1e-7)
    named = EquationsSystem(
        {**DRIVEN, "inputs": ["torque"], "equations": {"x": "v", "v": "-k*x + torque"}}, input={"file": str(path)}
    )
    assert named.generate(1, seed=0, dt=0.05, horizon=10).u.shape == (1, 11, 1, 1)  # column: the input's name
    bad = [
        ({"file": str(tmp_path / "none.csv")}, "does not exist"),
        ({"file": str(path), "column": "torqe"}, "has no column 'torqe'. Did you mean 'torque'"),
        ({"file": str(path), "column": "torque", "time_column": "time"}, "has no column 'time'"),
    ]
    for config, message in bad:
        with pytest.raises(ConfigError, match=re.escape(message)):
            EquationsSystem(DRIVEN, input=config).generate(1, seed=0, dt=0.05, horizon=10)
    with pytest.raises(ConfigError, match=r"covers t = 0 to 3 but the simulation runs from 0 to 5"):
        EquationsSystem(DRIVEN, input={"file": str(path), "column": "torque"}).generate(1, 0, dt=0.05, horizon=100)
    (tmp_path / "gap.csv").write_text("t,u\n0,1\n0.1,\n0.2,3\n")
    with pytest.raises(ConfigError, match=r"row 3, column 'u' is empty"):
        EquationsSystem(DRIVEN, input={"file": str(tmp_path / "gap.csv")}).generate(1, 0, dt=0.05, horizon=2)


@pytest.mark.parametrize(
    "changes, message",
    [
        ({}, "declares the inputs ['u'] but no signal drives them; set system.input"),
        ({"input": {"kind": "whitenoise"}}, "system.input.kind='whitenoise' is not a signal"),
        ({"input": {"kind": "prbs", "band": [1, 2]}}, "system.input.band is not a key of a prbs signal"),
        ({"input": {"kind": "multisine", "rms": 1, "amplitude": 1}}, "give amplitude (of each component) or rms"),
        ({"input": {"kind": "steps", "levels": [2, 1]}}, "system.input.levels must be [low, high] with low <= high"),
        ({"input": {"kind": "chirp", "hold": "cubic"}}, "system.input.hold='cubic': use zoh"),
        ({"input": {"kind": "prbs", "sequence": "gold"}}, "use mls (maximal length) or random"),
        ({"input": "multisine"}, "system.input must be a mapping"),
        ({"inputs": None, "equations": {"x": "v", "v": "-x"}, "input": {"kind": "chirp"}}, "declares no inputs"),
    ],
)
def test_driven_twin_keys_are_checked(changes, message):
    with pytest.raises(ConfigError) as err:
        EquationsSystem({**DRIVEN, **changes})
    assert message in str(err.value)


def test_several_inputs_each_with_its_own_signal():
    spec = {**DRIVEN, "inputs": ["u", "f"], "equations": {"x": "v", "v": "-k*x + u + f"}}
    both = EquationsSystem(spec, input={"u": {"kind": "chirp"}, "f": {"kind": "prbs", "clock": 0.2}})
    data = both.generate(2, seed=0, dt=0.05, horizon=40)
    assert data.control_names == ["u", "f"] and set(data.u[..., 1].unique().tolist()) == {-1.0, 1.0}
    with pytest.raises(ConfigError, match="the inputs' holds differ"):
        EquationsSystem(spec, input={"u": {"kind": "chirp"}, "f": {"kind": "prbs", "hold": "linear"}})
    with pytest.raises(ConfigError, match=r"gives signals for \['u'\] but not for the inputs \['f'\]"):
        EquationsSystem(spec, input={"u": {"kind": "chirp"}})
