"""Window rollouts (`mpsim.diagnose.windows`): batched windows of a time-invariant model are the windows rolled
out one by one; a model that reads absolute time keeps each window on its own times."""

from __future__ import annotations

import math

import pytest
import torch

from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.windows import window_predictions, window_starts
from mpsim.effects import DryFriction, PeriodicForcing
from mpsim.models.equations import EquationsModel
from mpsim.solvers.odeint import ODESolver

NONE = torch.zeros(2, 0, dtype=torch.long)
AXIS = {  # a driven mass with viscous friction (the input enters the equations, as a motor force)
    "states": ["q", "v"],
    "inputs": ["u"],
    "equations": {"q": "v", "v": "(u - c*v - k*q)/m"},
    "params": {"m": 2.0, "c": 1.5, "k": 30.0},
    "nodes": 1,
}


def _data(b: int = 3, n_t: int = 47, dt: float = 0.01) -> Trajectories:
    """Random states and a random zero-order-hold input: the windows only need observed starts to roll from."""
    gen = torch.Generator().manual_seed(0)
    t = torch.arange(n_t, dtype=torch.float64) * dt
    x = torch.randn(b, n_t, 1, 2, generator=gen, dtype=torch.float64)
    u = torch.randn(b, n_t, 1, 1, generator=gen, dtype=torch.float64)
    meta = {"input_hold": "zoh", "control_names": ["u"], "state_names": ["q", "v"]}
    return Trajectories(t=t, x=x, edge_index=NONE, u=u, meta=meta)


def _model(spec: dict, effects=(), solver: ODESolver | None = None) -> EquationsModel:
    solver = solver or ODESolver("rk4", step_size=0.0025)
    model = EquationsModel(2, 1, spec=spec, solver=solver, effects=list(effects)).double()
    model.bind_effects(["q", "v"])
    return model


def _one_by_one(model: EquationsModel, data: Trajectories, length: int) -> list[torch.Tensor]:
    out = []
    for s in window_starts(data.n_times, length):
        end = min(s + length, data.n_times - 1)
        out.append(model.rollout(data.x[:, s], data.t[s : end + 1], data.inputs(s, end + 1)))
    return out


@pytest.mark.parametrize("solver", [ODESolver("rk4", step_size=0.0025), ODESolver("dopri5", rtol=1e-9, atol=1e-11)])
def test_batched_windows_are_the_windows_one_by_one(solver, monkeypatch):
    model, data = _model(AXIS, [DryFriction(0.4, target="v")], solver), _data()
    assert model.time_invariant
    calls = []
    rollout = model.rollout
    monkeypatch.setattr(model, "rollout", lambda *a: calls.append(a[0].shape[0]) or rollout(*a))
    got = window_predictions(model, data, 10)  # 4 full windows of 10 steps and one of 6
    assert calls == [4 * 3, 3]  # the full windows as one batch of K·B records, then the short one
    want = _one_by_one(model, data, 10)
    assert [s for s, _ in got] == window_starts(data.n_times, 10)
    for (_, p), w in zip(got, want, strict=True):
        assert p.shape == w.shape
        assert torch.allclose(p, w, rtol=0, atol=1e-9)


def test_a_model_that_reads_time_keeps_each_window_on_its_own_times(monkeypatch):
    data = _data()
    drive = PeriodicForcing(amplitude=3.0, omega=2 * math.pi / 0.3, target="v")
    spec_t = {**AXIS, "equations": {"q": "v", "v": "(u + sin(7*t) - c*v - k*q)/m"}}
    for model in (_model(AXIS, [drive]), _model(spec_t)):
        assert not model.time_invariant
        calls = []
        rollout = model.rollout
        monkeypatch.setattr(
            model, "rollout", lambda *a, calls=calls, rollout=rollout: calls.append(a[1][0]) or rollout(*a)
        )
        got = window_predictions(model, data, 10)
        assert [float(t0) for t0 in calls] == pytest.approx([float(data.t[s]) for s in window_starts(47, 10)])
        for (_, p), w in zip(got, _one_by_one(model, data, 10), strict=True):
            assert torch.equal(p, w)
