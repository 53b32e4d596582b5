"""Multiple-shooting fits and held-out window errors (`mpsim.diagnose.shooting`)."""

from __future__ import annotations

import math

import pytest
import torch

from mpsim.diagnose.shooting import (
    horizon_from_data,
    null_data,
    sandwich_stderr,
    shooting_fit,
    window_error,
    with_effect,
)
from mpsim.effects import CubicStiffness, LinearDamping
from mpsim.models.equations import EquationsModel
from mpsim.solvers.odeint import ODESolver
from mpsim.systems.equations import EquationsSystem

OSC = {
    "states": ["x", "v"],
    "equations": {"x": "v", "v": "-k*x"},
    "params": {"k": 4.0},
    "nodes": 1,
    "init": {"x": [-1, 1], "v": [-1, 1]},
}


def _model():
    model = EquationsModel(2, spec=OSC, solver=ODESolver("dopri5", rtol=1e-8, atol=1e-9)).double()
    model.set_normalisation(torch.zeros(2, dtype=torch.float64), torch.ones(2, dtype=torch.float64))
    return model


def test_damping_from_coarse_semi_implicit_euler_data_is_unbiased():
    # data stepped like a rigid-body engine (h = 0.005, logged every 10th step): a one-step regression inherits
    # the stepping; shooting through the model's own integrator does not
    truth = {**OSC, "integrator": "semi_implicit_euler", "substep": 0.005}
    data = EquationsSystem(truth, effects=[LinearDamping(0.3, target="v")]).generate(8, seed=0, dt=0.05, horizon=100)
    trial = with_effect(_model(), LinearDamping(0.05, target="v").bind(["x", "v"]))
    fit = shooting_fit(trial, data, 20, [trial.effects[-1].coef, trial.raw["k"]], iters=30)
    assert fit.converged
    assert fit.values[0] == pytest.approx(0.3, rel=0.05)
    assert float(trial.parameters_now()["k"].detach()) == pytest.approx(4.0, rel=0.01)
    lo, hi = fit.values[0] - 1.96 * fit.stderr[0], fit.values[0] + 1.96 * fit.stderr[0]
    assert lo < fit.values[0] < hi and hi - lo < 0.1


def test_window_error_horizon_and_null_data():
    model = _model()
    data = EquationsSystem(OSC).generate(6, seed=1, dt=0.1, horizon=40)
    assert float(window_error(model, data, 10).max()) < 1e-10  # the model is the truth
    assert horizon_from_data(model, data, 0.3) == 40  # never loses track: the whole record
    wrong = EquationsModel(2, spec={**OSC, "params": {"k": 6.0}}).double()
    wrong.set_normalisation(torch.zeros(2, dtype=torch.float64), torch.ones(2, dtype=torch.float64))
    assert 2 <= horizon_from_data(wrong, data, 0.3) < 40
    assert float(window_error(wrong, data, 5).mean()) < float(window_error(wrong, data, 40).mean())
    noisy = null_data(model, data, torch.tensor([0.01, 0.02]), seed=0)
    diff = (noisy.x - data.x).reshape(-1, 2)
    assert diff.std(0).tolist() == pytest.approx([0.01, 0.02], rel=0.15)


def test_segmented_null_data_restart_every_window_from_an_observed_state():
    """Chaotic records are judged over short windows: their null data are windows simulated from observed
    states (one null record each), not a whole-record simulation that leaves the data's attractor."""
    lorenz = {
        "states": ["x", "y", "z"],
        "equations": {"x": "s*(y - x)", "y": "x*(r - z) - y", "z": "x*y - b*z"},
        "params": {"s": 10.0, "r": 28.0, "b": 2.6667},
        "nodes": 1,
        "init": {"x": [-10, 10], "y": [-10, 10], "z": [10, 30]},
    }
    data = EquationsSystem(lorenz).generate(3, seed=0, dt=0.02, horizon=60)
    model = EquationsModel(3, spec=lorenz, solver=ODESolver("dopri5", rtol=1e-8, atol=1e-9)).double()
    model.set_normalisation(torch.zeros(3, dtype=torch.float64), torch.full((3,), 8.0, dtype=torch.float64))
    null = null_data(model, data, torch.zeros(3), seed=0, segment=10)
    assert null.x.shape == (6 * 3, 11, 1, 3)  # 6 windows of 10 steps × 3 records
    assert torch.allclose(null.t, data.t[:11].to(null.t))
    assert torch.allclose(null.x[3:6, 0], data.x[:, 10].double())  # window 2 starts at the observed step 10
    assert float(window_error(model, null, 10).max()) < 1e-8  # the model predicts its own null data
    # a model a little off (r 28.05 for 28) over 5 s of chaos: its whole-record simulation leaves the data,
    # its windows stay near them
    data = EquationsSystem(lorenz).generate(3, seed=0, dt=0.02, horizon=250)
    model.raw["r"].data.fill_(math.log(28.05))  # positive constants live in log space
    whole = null_data(model, data, torch.zeros(3), seed=0)
    windows = null_data(model, data, torch.zeros(3), seed=0, segment=10)
    far = float((whole.x[:, -1] - data.x[:, -1].double()).abs().max())
    near = float((windows.x[-3:, -1] - data.x[:, 250].double()).abs().max())
    assert far > 10.0 * near, (far, near)


def test_raw_unit_coefficient_of_1e5_moves_from_a_third_of_its_value():
    """A cubic stiffness in SI units (coef 1.6e5 /(m² s²) on positions of 1e-2 m) beside log-parametrised
    constants: the fit steps in curvature-scaled units, so the coefficient moves to its value (in float32, as
    `trainer=whitebox` stores a model). Data from a fixed-step RK4 written here, not mpsim's simulator."""
    k, c3, dt, steps = 200.0, 1.6e5, 0.002, 150

    def field(x: torch.Tensor) -> torch.Tensor:  # [B, 2]
        return torch.stack([x[:, 1], -k * x[:, 0] - c3 * x[:, 0] ** 3], dim=-1)

    gen = torch.Generator().manual_seed(0)
    x = torch.cat([torch.rand(6, 1, generator=gen, dtype=torch.float64) * 0.04 - 0.02, torch.zeros(6, 1)], dim=1)
    xs = [x]
    for _ in range(steps * 4):  # 4 RK4 substeps per sample
        h = dt / 4
        k1 = field(x)
        k2 = field(x + h / 2 * k1)
        k3 = field(x + h / 2 * k2)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + field(x + h * k3))
        xs.append(x)
    traj = torch.stack(xs[::4], dim=1)[:, :, None, :]  # [B, T, 1, 2]
    data = EquationsSystem(OSC).generate(6, seed=0, dt=dt, horizon=steps)
    data = type(data)(t=data.t, x=traj, edge_index=data.edge_index, meta=data.meta)
    model = EquationsModel(2, spec={**OSC, "params": {"k": 190.0}}, solver=ODESolver("rk4", step_size=dt / 2))
    model.set_normalisation(torch.zeros(2), traj.reshape(-1, 2).std(0).float())
    trial = with_effect(model, CubicStiffness(c3 / 3, target="v", source="x").bind(["x", "v"]))
    fit = shooting_fit(trial, data, 50, [trial.effects[-1].coef, trial.raw["k"]], iters=30)
    assert fit.converged
    assert fit.values[0] == pytest.approx(c3, rel=0.02)
    assert float(trial.parameters_now()["k"].detach()) == pytest.approx(k, rel=0.01)


def test_a_fit_whose_values_are_never_reported_skips_its_standard_errors():
    data = EquationsSystem(OSC, effects=[LinearDamping(0.3, target="v")]).generate(4, seed=0, dt=0.1, horizon=30)
    trial = with_effect(_model(), LinearDamping(0.1, target="v").bind(["x", "v"]))
    fit = shooting_fit(trial, data, 10, [trial.effects[-1].coef], iters=10, stderr=False)
    assert fit.converged and fit.values[0] == pytest.approx(0.3, rel=0.01)
    assert all(math.isnan(v) for v in fit.stderr)


# −c·x³ with c = −3.6e12 blows up within a microsecond: dopri5's step underflows (issue 71, item 5)
RUN_OFF = -3.6e12


def _run_off_trial(coef: float):
    return with_effect(_model(), CubicStiffness(coef, target="v", source="x").bind(["x", "v"]))


def test_a_fit_that_cannot_start_is_not_converged_and_says_why():
    data = EquationsSystem(OSC).generate(4, seed=0, dt=0.1, horizon=30)
    trial = _run_off_trial(RUN_OFF)  # the screen's coefficient, where every rollout fails
    fit = shooting_fit(trial, data, 10, [trial.effects[-1].coef], iters=5)  # raised DivergenceError before
    assert not fit.converged and fit.values == fit.stopped_at == [RUN_OFF]
    assert fit.failure.startswith("ODE solver failed (") and " at t=" in fit.failure
    assert all(math.isnan(v) for v in fit.stderr)


def test_a_fit_that_ends_where_the_solver_fails_is_set_back_to_its_start(monkeypatch):
    """An L-BFGS line search can stop on a point it never evaluated as a failure (unmeasured starts are estimated
    afresh at the end): the fit goes back to where it started and says where it had run to."""
    import mpsim.diagnose.shooting as shooting

    lbfgs = shooting._lbfgs

    def runs_off(model, *args, **kwargs):
        loss = lbfgs(model, *args, **kwargs)
        model.effects[-1].coef.data.fill_(RUN_OFF)
        return loss

    monkeypatch.setattr(shooting, "_lbfgs", runs_off)
    data = EquationsSystem(OSC, effects=[CubicStiffness(0.5, target="v", source="x")]).generate(
        4, seed=0, dt=0.1, horizon=30
    )
    trial = _run_off_trial(0.1)
    fit = shooting_fit(trial, data, 10, [trial.effects[-1].coef], iters=5)  # raised DivergenceError before
    assert not fit.converged and fit.values == [pytest.approx(0.1)] and fit.stopped_at == [RUN_OFF]
    assert float(trial.effects[-1].coef.detach()[0]) == pytest.approx(0.1)
    assert "ODE solver failed" in fit.failure


def test_standard_errors_where_every_rollout_fails_are_nan():
    data = EquationsSystem(OSC).generate(4, seed=0, dt=0.1, horizon=30)
    trial = _run_off_trial(RUN_OFF)
    coef = trial.effects[-1].coef
    assert all(math.isnan(v) for v in sandwich_stderr(trial, data, 10, [coef]))  # raised DivergenceError before
    assert float(coef.detach()[0]) == RUN_OFF  # no difference step left behind


def test_few_heldout_records_are_scored_over_shorter_windows():
    from mpsim.diagnose.shooting import scored_window

    assert scored_window(4, 101, 100) == 34  # four 1 s segments of 100 steps: three windows each (34, 34, 32)
    assert scored_window(16, 101, 100) == 100  # enough records: the horizon
    assert scored_window(4, 21, 100) == 10  # never below MIN_TEST_WINDOW steps
    assert scored_window(4, 101, 8) == 8  # nor above the horizon
