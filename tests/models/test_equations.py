"""`model=equations`: every example spec recovers its learnable parameters from data simulated from it
(wrong starting values, mpsim's trainer), per-trajectory graphs, sensitivities, checkpoints and refusals."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from mpsim.commands.eval import run_eval
from mpsim.commands.train import run_train
from mpsim.data.dataset import fit_normalisation
from mpsim.data.trajectories import Inputs
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
SLOW = ["fitzhugh_nagumo", "pendulum_inertia", "pendulums_bob_spring"]


def _fit(name, tmp_path, n=6):
    spec = load_spec_file(EXAMPLES / f"{name}.yaml")
    system = EquationsSystem(spec)
    train, val = system.generate(n, seed=0), system.generate(2, seed=1)
    start = {p: (system.spec.params[p] * 1.2).tolist() for p in system.spec.learnable}  # 20 % off
    model = EquationsModel(
        system.spec.state_dim, spec=spec, init=start, solver=ODESolver("dopri5", rtol=1e-7, atol=1e-8)
    ).double()
    model.bind_effects(train.state_names)
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
