"""`model=equations`: every example spec recovers its learnable parameters from data simulated from it
(wrong starting values, mpsim's trainer), per-trajectory graphs, sensitivities, checkpoints and refusals."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from mpsim.commands.eval import run_eval
from mpsim.commands.train import run_train
from mpsim.data.dataset import fit_normalisation
from mpsim.data.trajectories import Inputs, Trajectories
from mpsim.effects import LinearDamping
from mpsim.errors import ConfigError, IncompatibleError
from mpsim.models.equations import EquationsModel
from mpsim.solvers.odeint import ODESolver
from mpsim.spec import load_spec_file
from mpsim.systems.equations import EquationsSystem
from mpsim.training.checkpoint import load_checkpoint
from mpsim.training.trainer import Trainer

EXAMPLES = Path(__file__).resolve().parents[2] / "examples" / "equations"
FAST = ["kuramoto_frequencies", "lorenz_network", "pendulums_linear_spring"]
SLOW = ["driven_pendulum", "fitzhugh_nagumo", "lorenz96", "pendulum_inertia", "pendulums_bob_spring"]


def _fit(name, tmp_path, n=6):
    spec = load_spec_file(EXAMPLES / f"{name}.yaml")
    system = EquationsSystem(spec)
    train, val = system.generate(n, seed=0), system.generate(2, seed=1)
    start = {p: (system.spec.params[p] * 1.2).tolist() for p in system.spec.learnable}  # 20 % off
    model = EquationsModel(
        system.spec.state_dim,
        system.control_dim,
        spec=spec,
        init=start,
        solver=ODESolver("dopri5", rtol=1e-7, atol=1e-8),
    ).double()
    model.bind_effects(train.state_names)
    model.bind_inputs(train.control_names)
    model.set_normalisation(*fit_normalisation(train))
    trainer = Trainer(
        optimizer="lbfgs",
        lr=1.0,
        batch_size=64,
        max_epochs=12,
        plateau_patience=3,
        early_stop_patience=4,
        progress=False,
    )
    trainer.fit(model, train, val, run_dir=tmp_path, checkpoint_base={"model": {}})
    fitted = model.parameters_now()
    return {
        p: float(((fitted[p].detach() - v).abs() / v.abs()).max())
        for p, v in system.spec.params.items()
        if p in system.spec.learnable
    }


@pytest.mark.parametrize("name", FAST)
def test_examples_recover_their_parameters(name, tmp_path):
    errors = _fit(name, tmp_path)
    assert errors and max(errors.values()) < 0.01, errors


@pytest.mark.slow
@pytest.mark.parametrize("name", SLOW)
def test_slower_examples_recover_their_parameters(name, tmp_path):
    errors = _fit(name, tmp_path)
    assert errors and max(errors.values()) < 0.01, errors


def test_every_example_is_in_a_recovery_test():
    assert sorted(FAST + SLOW) == sorted(p.stem for p in EXAMPLES.glob("*.yaml"))


SPRING = {
    "states": ["x", "v"],
    "equations": {"x": "v", "v": "-k*x + c*sum_nbr(x_j - x)"},
    "params": {"k": 1.0, "c": [0.5, 1.0, 1.5]},
}


def test_each_trajectory_runs_on_its_own_graph():
    model = EquationsModel(2, spec=SPRING, solver=ODESolver("rk4", step_size=0.01)).double()
    graphs = [torch.tensor([[0, 1], [1, 0]]), torch.tensor([[1, 2, 0], [2, 1, 1]])]
    padded = torch.full((2, 2, 3), -1)
    padded[0, :, :2], padded[1] = graphs[0], graphs[1]
    x0 = torch.randn(2, 3, 2, dtype=torch.float64)
    t = torch.linspace(0, 1, 11, dtype=torch.float64)
    together = model.rollout(x0, t, Inputs(padded))
    for b, g in enumerate(graphs):
        assert torch.allclose(together[b], model.rollout(x0[b : b + 1], t, Inputs(g))[0], atol=1e-12)
    assert not torch.allclose(together[0], together[1])


def test_sensitivities_match_finite_differences_and_shifts_apply():
    model = EquationsModel(2, spec=SPRING).double()
    ei = torch.tensor([[0, 1, 1, 2], [1, 0, 2, 1]])
    x = torch.randn(5, 3, 2, dtype=torch.float64)
    sens = model.sensitivities(torch.tensor(0.0), x, ei)
    assert model.sensitivity_names() == ["k", "c[0]", "c[1]", "c[2]"] and sens.shape == (5, 3, 2, 4)
    base = model.parameters_now()

    def field(**change):
        from mpsim.graphs.batch import batch_graph

        values = {**{k: v.detach() for k, v in base.items()}, **change}
        return model.field(torch.tensor(0.0), x, values, batch_graph(ei, 5, 3, dtype=x.dtype))

    h = 1e-6
    assert torch.allclose(sens[..., 0], (field(k=base["k"].detach() + h) - field()) / h, atol=1e-6)
    bumped = base["c"].detach().clone()
    bumped[2] += h
    assert torch.allclose(sens[..., 3], (field(c=bumped) - field()) / h, atol=1e-6)
    model.shift_parameters({"k": 0.25, "c[1]": -0.5})
    now = model.parameters_now()
    now = {k: v.detach() for k, v in now.items()}
    assert float(now["k"]) == pytest.approx(1.25) and now["c"].tolist() == pytest.approx([0.5, 0.5, 1.5])
    model.shift_parameters({"c[0]": -1.0})  # would make a positive constant negative: not applied
    assert float(model.parameters_now()["c"][0].detach()) == pytest.approx(0.5)


def test_learnable_effects_train_beside_the_spec(tmp_path):
    spec = {
        "states": ["x", "v"],
        "equations": {"x": "v", "v": "-k*x"},
        "params": {"k": 2.0},
        "learnable": [],
        "nodes": 1,
        "init": {"x": [-1, 1], "v": [-1, 1]},
        "dt": 0.1,
        "horizon": 40,
    }
    data = EquationsSystem(spec, effects=[LinearDamping(0.4, target="v")]).generate(6, seed=0)
    model = EquationsModel(
        2, spec=spec, effects=[LinearDamping(0.1, target="v")], solver=ODESolver("dopri5", rtol=1e-7, atol=1e-8)
    ).double()
    model.bind_effects(data.state_names)
    model.set_normalisation(*fit_normalisation(data))
    Trainer(optimizer="lbfgs", lr=1.0, batch_size=64, max_epochs=8, progress=False).fit(
        model, data, data, run_dir=tmp_path, checkpoint_base={"model": {}}
    )
    assert float(model.effects[0].coef.detach()[0]) == pytest.approx(0.4, rel=0.01)


def test_spec_must_fit_the_data():
    model = EquationsModel(2, spec=SPRING)
    with pytest.raises(IncompatibleError, match="written for 3 nodes .* data has 4"):
        model.check_compatible(2, 0, 4)
    with pytest.raises(ConfigError, match=r"do not match the data's states \['v', 'x'\].*another order"):
        model.bind_effects(["v", "x"])
    with pytest.raises(ConfigError, match="has 2 states"):
        EquationsModel(3, spec=SPRING)
    with pytest.raises(ConfigError, match="no equations"):
        EquationsModel(2)
    with pytest.raises(ConfigError, match="is a file name"):
        EquationsModel(2, spec="my_spec.yaml")
    with pytest.raises(ConfigError, match="model.init.q: not a learnable"):
        EquationsModel(2, spec=SPRING, init={"q": 1.0})


def test_command_line_round_trip_keeps_the_spec_in_the_checkpoint(cfg_factory, tmp_path):
    spec_file = tmp_path / "osc.yaml"
    spec_file.write_text(
        "states: [x, v]\nequations: {x: v, v: -k*x - c*v}\nparams: {k: 3.0, c: 0.2}\n"
        "learnable: [k, c]\nnodes: 2\ninit: {x: [-1, 1], v: [-1, 1]}\ndt: 0.1\nhorizon: 30\n"
    )
    common = [
        "system=equations",
        f"system.spec={spec_file}",
        "data.n_train=8",
        "data.n_val=2",
        "data.n_test=2",
        "eval.horizons=[1,10]",
        "eval.plots=false",
        "trainer=whitebox",
        "trainer.progress=false",
    ]
    summary = run_train(
        cfg_factory("train", "model=equations", f"model.spec={spec_file}", "model.init={k: 2.5}", *common),
        output_dir=tmp_path / "run",
    )
    assert summary["model"]["physical_parameters"]["k"] == pytest.approx(3.0, rel=0.01)
    assert summary["system"]["name"] == "osc"
    spec_file.unlink()  # the checkpoint carries the equations, not the file name
    ckpt = load_checkpoint(summary["exported"])
    assert ckpt["model"]["config"]["spec"]["equations"] == {"x": "v", "v": "-k*x - c*v"}
    system_spec = ckpt["system"]["params"]["spec"]
    assert system_spec["params"] == {"k": 3.0, "c": 0.2}
    out = run_eval(
        cfg_factory(
            "eval",
            f"init={summary['exported']}",
            "system=equations",
            "system.spec={states: [x, v], equations: {x: v, v: -3*x - 0.2*v}, nodes: 2}",
            "data.n_test=2",
            "data.horizon=30",
            "eval.horizons=[1,10]",
            "eval.plots=false",
        ),
        output_dir=tmp_path / "eval",
    )
    assert out["test"]["rmse"] < 1e-2


@pytest.mark.slow  # 3–6 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_lorenz96_on_a_chain_trains_on_the_command_line(cfg_factory, tmp_path):
    """The ring example's file on a chain with zero padding (system.graph, system.shift_boundary and
    model.shift_boundary on the command line): F is recovered from 10 % off, and the checkpoint keeps the boundary."""
    spec = EXAMPLES / "lorenz96.yaml"
    summary = run_train(
        cfg_factory(
            "train",
            "system=equations",
            f"system.spec={spec}",
            "system.graph=chain",
            "system.shift_boundary=0.0",
            "model=equations",
            f"model.spec={spec}",
            "model.shift_boundary=0.0",
            "model.init={F: 7.2}",
            "data.n_train=6",
            "data.n_val=2",
            "data.n_test=2",
            "data.horizon=20",
            "eval.horizons=[1,10]",
            "eval.plots=false",
            "trainer=whitebox",
            "trainer.max_epochs=6",
            "trainer.progress=false",
        ),
        output_dir=tmp_path / "run",
    )
    assert summary["model"]["physical_parameters"]["F"] == pytest.approx(8.0, rel=1e-3)
    ckpt = load_checkpoint(summary["exported"])
    assert ckpt["model"]["config"]["shift_boundary"] == 0.0
    with pytest.raises(ConfigError, match="not a ring"):
        EquationsModel(1, spec={**load_spec_file(spec), "graph": "chain"})


def test_batched_one_step_equals_step_by_step_with_time_and_effects():
    from mpsim.effects import PeriodicForcing
    from mpsim.models.capabilities import one_step_by_rollouts

    spec = {
        "states": ["x", "v"],
        "equations": {"x": "v", "v": "-k*x + 0.3*sin(2*t) + c*sum_nbr(x_j - x)"},
        "params": {"k": 2.0, "c": 0.5},
    }
    model = EquationsModel(
        2,
        spec=spec,
        effects=[PeriodicForcing(0.5, 3.0, 0.2, target=1)],
        solver=ODESolver("dopri5", rtol=1e-10, atol=1e-12),
    ).double()
    model.bind_effects(["x", "v"])
    x = torch.randn(3, 12, 4, 2, dtype=torch.float64)
    t = torch.arange(12, dtype=torch.float64) * 0.1 + 0.7  # absolute times: the drive's phase must follow them
    ei = torch.tensor([[0, 1, 2, 3, 1, 2], [1, 2, 3, 0, 0, 1]])
    batched, stepwise = model.one_step(x, t, Inputs(ei)), one_step_by_rollouts(model, x, t, Inputs(ei))
    assert batched.shape == (3, 11, 4, 2)
    assert torch.allclose(batched, stepwise, atol=1e-8)


# ---- driven specs (issue 60): inputs from the data's controls, matched by name, held as the data say ----------
DRIVEN = {
    "states": ["x", "v"],
    "inputs": ["u"],
    "equations": {"x": "v", "v": "-k*x + u"},
    "params": {"k": 4.0},
    "nodes": 1,
}
NONE = torch.zeros(2, 0, dtype=torch.long)


def _exact(x0, t, u, hold, k=4.0):
    """[B, T, 2] the exact solution of x'' = −k x + u from x0 [B, 2], with u [B, T] held (zoh) or interpolated
    (linear) between samples: on each interval u = a + b·τ has the particular solution ((a + bτ)/k, b/k)."""
    w = k**0.5
    out, s = [x0], x0
    for i in range(t.numel() - 1):  # a loop in time only (the reference)
        h = float(t[i + 1] - t[i])
        a = u[:, i]
        b = torch.zeros_like(a) if hold == "zoh" else (u[:, i + 1] - a) / h
        ex, ev = s[:, 0] - a / k, s[:, 1] - b / k
        c, sn = torch.cos(torch.tensor(w * h, dtype=torch.float64)), torch.sin(torch.tensor(w * h, dtype=torch.float64))
        s = torch.stack([(a + b * h) / k + ex * c + ev / w * sn, b / k - ex * w * sn + ev * c], -1)
        out.append(s)
    return torch.stack(out, 1)


def _driven_model(spec=DRIVEN, rtol=1e-10, **kw):
    return EquationsModel(2, 1, spec=spec, solver=ODESolver("dopri5", rtol=rtol, atol=rtol * 1e-2), **kw).double()


def _inputs(u, hold, names=("u",)):  # u: [B, T] one node, one input
    return Inputs(NONE, u[:, :, None, None], None, {"input_hold": hold, "control_names": list(names)})


@pytest.mark.parametrize("hold", ["zoh", "linear"])
def test_a_driven_spring_follows_the_closed_form(hold):
    model, t = _driven_model(), torch.linspace(0, 3, 31, dtype=torch.float64)
    step = torch.full((1, 31), 2.0, dtype=torch.float64)  # a constant step from rest: x = u/k (1 − cos 2t)
    out = model.rollout(torch.zeros(1, 1, 2, dtype=torch.float64), t, _inputs(step, hold))[:, :, 0, 0]
    assert torch.allclose(out[0], 0.5 * (1 - torch.cos(2 * t)), atol=1e-8)
    x0 = torch.tensor([[0.3, -0.2], [0.0, 0.0]], dtype=torch.float64)
    u = torch.stack([torch.sin(3 * t), 1 + 0.5 * torch.cos(1.3 * t)])  # sampled sinusoids
    out = model.rollout(x0[:, None], t, _inputs(u, hold))[:, :, 0]
    assert torch.allclose(out, _exact(x0, t, u, hold), atol=1e-8)


def test_linear_hold_is_closer_than_zoh_to_the_continuous_sine():
    model, t = _driven_model(), torch.linspace(0, 3, 61, dtype=torch.float64)
    u = torch.sin(3 * t)[None]  # the continuous drive, sampled: x = (sin 3t − 1.5 sin 2t)/(4 − 9)
    truth = (torch.sin(3 * t) - 1.5 * torch.sin(2 * t)) / (4 - 9)
    x0 = torch.zeros(1, 1, 2, dtype=torch.float64)
    with torch.no_grad():
        err = {
            h: float((model.rollout(x0, t, _inputs(u, h))[0, :, 0, 0] - truth).abs().max()) for h in ("zoh", "linear")
        }
    assert err["linear"] < 1e-3 < err["zoh"] and err["linear"] < err["zoh"] / 10, err


@pytest.mark.parametrize("hold", ["zoh", "linear"])
def test_driven_one_step_is_every_interval_with_its_own_input(hold):
    from mpsim.models.capabilities import one_step_by_rollouts

    model, t = _driven_model(), torch.arange(12, dtype=torch.float64) * 0.1 + 0.4
    x = torch.randn(3, 12, 1, 2, dtype=torch.float64)
    u = torch.randn(3, 12, dtype=torch.float64)
    batched = model.one_step(x, t, _inputs(u, hold))
    assert batched.shape == (3, 11, 1, 2)
    assert torch.allclose(batched, one_step_by_rollouts(model, x, t, _inputs(u, hold)), atol=1e-9)
    for k in (0, 5, 10):
        exact = _exact(x[:, k, 0], t[k : k + 2], u[:, k : k + 2], hold)[:, 1]
        assert torch.allclose(batched[:, k, 0], exact, atol=1e-9)


def test_driven_sensitivities_are_taken_with_their_inputs():
    from mpsim.diagnose.nuisance import model_sensitivities
    from mpsim.graphs.batch import batch_graph

    spec = {
        **DRIVEN,
        "equations": {"x": "v", "v": "(g*u - k*x - c*v)/M"},
        "params": {"k": 4.0, "c": 0.2, "g": 1.5, "M": 2.0},
    }
    model = _driven_model(spec)
    x, u = torch.randn(7, 1, 2, dtype=torch.float64), torch.randn(7, 1, 1, dtype=torch.float64)
    sens = model.sensitivities(torch.tensor(0.0), x, NONE, u=u)
    assert model.sensitivity_names() == ["k", "c", "g", "M"] and sens.shape == (7, 1, 2, 4)
    base = {k: v.detach() for k, v in model.parameters_now().items()}
    graph = batch_graph(NONE, 7, 1, dtype=x.dtype)

    def field(**change):
        return model.field(torch.tensor(0.0), x, {**base, **change}, graph, u)

    for i, name in enumerate(model.sensitivity_names()):
        h = 1e-6
        fd = (field(**{name: base[name] + h}) - field(**{name: base[name] - h})) / (2 * h)
        assert torch.allclose(sens[..., i], fd, atol=1e-7), name
    assert torch.allclose(sens[:, 0, 1, 2], u[:, 0, 0] / 2.0)  # ∂f_v/∂g = u/M
    with pytest.raises(ConfigError, match="need the inputs"):
        model.sensitivities(torch.tensor(0.0), x, NONE)
    # the residual loop's step-averaged sensitivities: under zoh step k's input is u_k at both ends
    t = torch.arange(5, dtype=torch.float64) * 0.1
    xs, us = torch.randn(2, 5, 1, 2, dtype=torch.float64), torch.randn(2, 5, 1, 1, dtype=torch.float64)
    for hold in ("zoh", "linear"):
        data = Trajectories(t, xs, NONE, u=us, meta={"input_hold": hold, "control_names": ["u"]})
        avg = model_sensitivities(model, data)
        assert avg.shape == (2, 4, 1, 2, 4)
        end_u = us[:, :-1] if hold == "zoh" else us[:, 1:]
        one = model.sensitivities(t[1:2], xs[:, 1], NONE, u=us[:, 0])  # step 0's end, trajectory 0 and 1
        start = model.sensitivities(t[0:1], xs[:, 0], NONE, u=us[:, 0])
        end = model.sensitivities(t[1:2], xs[:, 1], NONE, u=end_u[:, 0])
        assert torch.allclose(avg[:, 0], 0.5 * (start + end), atol=1e-12)
        assert hold == "linear" or torch.allclose(avg[:, 0], 0.5 * (start + one), atol=1e-12)


def test_controls_are_matched_to_the_inputs_by_name():
    fix = "data.control_columns=[...] (in the spec's order) or data.columns={<input>: <column>}"
    with pytest.raises(ConfigError, match=r"inputs \['u'\] are 1 per node but the data have 0") as err:
        EquationsModel(2, 0, spec=DRIVEN)
    assert fix in str(err.value)
    with pytest.raises(ConfigError, match="declares no inputs but the data have 2 control"):
        EquationsModel(2, 2, spec=SPRING)
    with pytest.raises(ConfigError, match=r"inputs \['u'\] are 1 per node but the data have 2"):
        EquationsModel(2, 2, spec=DRIVEN)
    model = EquationsModel(2, 1, spec=DRIVEN)
    model.bind_inputs(["u"])
    with pytest.raises(ConfigError, match=r"inputs \['u'\] do not match the data's controls \['tau'\]") as err:
        model.bind_inputs(["tau"])
    assert fix in str(err.value) and "missing ['u'], extra ['tau']" in str(err.value)
    two = EquationsModel(2, 2, spec={**DRIVEN, "inputs": ["u", "f"], "equations": {"x": "v", "v": "u*f"}})
    with pytest.raises(ConfigError, match="the same names in another order"):
        two.bind_inputs(["f", "u"])
    with pytest.raises(ConfigError, match="a control the equations do not use is refused"):
        model.bind_inputs(["u", "f"])
    with pytest.raises(IncompatibleError, match="the data have 0 control"):
        model.check_compatible(2, 0, 1)
    t, u = torch.linspace(0, 1, 5, dtype=torch.float64), torch.zeros(1, 5, dtype=torch.float64)
    x0 = torch.zeros(1, 1, 2, dtype=torch.float64)
    with pytest.raises(ConfigError, match=r"do not match the data's controls \['F'\]"):
        model.double().rollout(x0, t, _inputs(u, "zoh", names=["F"]))
    with pytest.raises(ConfigError, match="input_hold='cubic' is not a hold"):
        model.rollout(x0, t, _inputs(u, "cubic"))
    with pytest.raises(ConfigError, match=r"need the controls \[B, T, N, C\] = \[1, 5, 1, 1\].* got no controls"):
        model.rollout(x0, t, Inputs(NONE))


def test_linear_damping_acts_on_the_rows_of_a_driven_model(tmp_path):
    spec = {
        **DRIVEN,
        "learnable": [],
        "init": {"x": [-1, 1], "v": [-1, 1]},
        "dt": 0.1,
        "horizon": 30,
        "input": {"kind": "multisine", "band": [0.2, 1.5], "components": 4, "hold": "zoh"},
    }
    data = EquationsSystem(spec, effects=[LinearDamping(0.4, target="v")]).generate(4, seed=0)
    assert data.u.shape == (4, 31, 1, 1) and data.meta["input_hold"] == "zoh"
    model = _driven_model(spec, rtol=1e-7, effects=[LinearDamping(0.1, target="v")])
    model.bind_effects(data.state_names)
    model.bind_inputs(data.control_names)
    model.set_normalisation(*fit_normalisation(data))
    Trainer(optimizer="lbfgs", lr=1.0, batch_size=64, max_epochs=6, progress=False).fit(
        model, data, data, run_dir=tmp_path, checkpoint_base={"model": {}}
    )
    assert float(model.effects[0].coef.detach()[0]) == pytest.approx(0.4, rel=0.01)


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_a_driven_twin_trains_on_the_command_line_and_its_checkpoint_round_trips(cfg_factory, tmp_path):
    spec_file = tmp_path / "driven.yaml"
    spec_file.write_text(
        "states: [x, v]\ninputs: [u]\nequations: {x: v, v: (g*u - k*x - c*v)/M}\n"
        "params: {k: 3.0, c: 0.2, g: 1.5, M: 1.0}\nlearnable: [k, c]\nnodes: 1\n"
        "init: {x: [-1, 1], v: [-1, 1]}\ndt: 0.1\nhorizon: 30\n"
        "input: {kind: prbs, amplitude: 1.0, clock: 0.3, hold: zoh, seed: 3}\n"
    )
    common = [
        "system=equations",
        f"system.spec={spec_file}",
        "data.n_train=6",
        "data.n_val=2",
        "data.n_test=2",
        "eval.horizons=[1,10]",
        "eval.plots=false",
        "trainer=whitebox",
        "trainer.progress=false",
        "dtype=float64",
    ]
    summary = run_train(
        cfg_factory("train", "model=equations", f"model.spec={spec_file}", "model.init={k: 2.5, c: 0.3}", *common),
        output_dir=tmp_path / "run",
    )
    fitted = summary["model"]["physical_parameters"]
    assert fitted["k"] == pytest.approx(3.0, rel=0.01) and fitted["c"] == pytest.approx(0.2, rel=0.01)
    assert summary["model"]["inputs"] == ["u"]
    ckpt = load_checkpoint(summary["exported"])
    assert ckpt["model"]["config"]["spec"]["inputs"] == ["u"] and ckpt["model"]["control_dim"] == 1
    out = run_eval(
        cfg_factory("eval", f"init={summary['exported']}", *common[:2], "data.n_test=2", *common[5:7]),
        output_dir=tmp_path / "eval",
    )
    assert out["test"]["rmse"] < 1e-2


def _belt_with_sensor(reads: str):
    """(spec, model) of a belt drive (states d, s, r; input u) whose sensor y reads `reads`."""
    spec = {"states": ["d", "s", "r"], "inputs": ["u"], "outputs": {"y": reads},
            "equations": {"d": "6.7*(1.8*u - d)", "s": "r", "r": "400*(d - s) - 13*r"}}  # fmt: skip
    model = EquationsModel(4, control_dim=1, spec=spec).double()
    model.bind_inputs(["u"])
    model.bind_effects(["d", "s", "r", "y"])
    return spec, model


def test_a_spec_with_outputs_appends_what_its_sensors_read():
    from mpsim.data.trajectories import Inputs

    spec, model = _belt_with_sensor("abs(s) + 0.5*u")
    t = 0.02 * torch.arange(40, dtype=torch.float64)
    u = torch.sign(torch.sin(3 * t)).reshape(1, 40, 1, 1)
    inputs = Inputs(torch.zeros(2, 0, dtype=torch.long), u=u, meta={"control_names": ["u"], "input_hold": "zoh"})
    out = model.rollout(torch.zeros(1, 1, 4, dtype=torch.float64), t, inputs)
    assert out.shape == (1, 40, 1, 4)
    assert torch.allclose(out[..., 3], out[..., 1].abs() + 0.5 * u[..., 0])  # read at every sample, input included
    step = model.one_step(out, t, inputs)  # from every sample: the states stepped, the outputs read at the end
    assert torch.allclose(step[..., 3], step[..., 1].abs() + 0.5 * u[:, 1:, :, 0])
    assert float((step - out[:, 1:]).abs().max()) < 1e-3
    with pytest.raises(ConfigError, match=r"3 states \['d', 's', 'r'\] and 1 outputs \['y'\] but the data has 3"):
        EquationsModel(3, control_dim=1, spec=spec)


def test_a_delayed_effect_on_a_spec_with_outputs_reads_the_states_history_only():
    # the residual loop's delayed candidates hand the record before a window as `Inputs.past`, all the data's columns
    # (states and the sensor's reading); the delay's history is the states' (a size mismatch on the coupled drives)
    from mpsim import effects as fx
    from mpsim.data.trajectories import Inputs

    _, model = _belt_with_sensor("abs(s)")
    model.effects.append(fx.DelayedFeedback(-1.0, delay=0.04, target="r", source="s").bind(["d", "s", "r", "y"]))
    t = 0.02 * torch.arange(20, dtype=torch.float64)
    u = torch.ones(1, 20, 1, 1, dtype=torch.float64)
    past = torch.zeros(1, 3, 1, 4, dtype=torch.float64)  # [B, P, N, D + outputs] the record before the window
    inputs = Inputs(
        torch.zeros(2, 0, dtype=torch.long), u=u, meta={"control_names": ["u"], "input_hold": "zoh"}, past=past
    )
    out = model.rollout(torch.zeros(1, 1, 4, dtype=torch.float64), t, inputs)
    assert out.shape == (1, 20, 1, 4) and bool(torch.isfinite(out).all())
    assert torch.allclose(out[..., 3], out[..., 1].abs())
