"""A delay is a number (issue 61, item 1): a delayed feedback's τ is fitted continuously by multiple shooting, not
chosen from the screen's grid of 1, 2, 4, 8 sampling steps, and reported with its 95 % interval.

The data come from a hand-written method-of-steps Euler at a fine step (not mpsim's delay integrator): a pendulum
whose velocity is fed back with gain c = −0.8 after τ = 0.15 s = 3 sampling steps, between the grid's 2 and 4.
The screen's start is the grid point below with its one-step gain; on the old code (τ fixed at the grid value) the
fit could only move the gain.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mpsim import effects as fx
from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.shooting import own_parameters, shooting_fit, window_predictions
from mpsim.diagnose.trial import fit_with, fitted_label, reported
from tests.diagnose.white_box import nominal_model

GL, GAIN, TAU = 9.81, -0.8, 0.15  # g/l, the feedback's gain and delay
H, DT, STEPS = 5e-4, 0.05, 100  # the generator's step; sampling interval (τ = 3 samples); 5 s records
NOMINAL = {
    "states": ["theta", "omega"],
    "equations": {"theta": "omega", "omega": "-(g/l)*sin(theta)"},
    "params": {"g": 9.81, "l": 1.0},
    "learnable": ["g"],
    "nodes": 1,
}


def delayed_pendulum(n: int, seed: int, tau: float = TAU) -> Trajectories:
    """θ'' = −(g/l) sin θ + c·θ'(t − τ) by forward Euler at h = 5e-4 (the method of steps: the delayed velocity is
    read from the stored fine-step history, held at its first value before t = 0), sampled every 0.05 s."""
    rng = np.random.default_rng(seed)
    theta, omega = rng.uniform(-2.0, 2.0, n), rng.uniform(-2.0, 2.0, n)  # [n] each
    every, lag = round(DT / H), round(tau / H)
    hist = np.empty((STEPS * every + 1, n))  # [S, n] the velocity at every fine step
    x = np.empty((n, STEPS + 1, 2))
    for s in range(STEPS * every + 1):  # the generator's time loop, vectorised over recordings
        hist[s] = omega
        if s % every == 0:
            x[:, s // every] = np.stack([theta, omega], axis=1)
        past = hist[max(s - lag, 0)]
        theta, omega = theta + H * omega, omega + H * (-GL * np.sin(theta) + GAIN * past)
    return Trajectories(
        t=torch.arange(STEPS + 1, dtype=torch.float64) * DT,
        x=torch.as_tensor(x)[:, :, None, :],
        edge_index=torch.zeros(2, 0, dtype=torch.long),
        meta={"state_names": ["theta", "omega"]},
    )


@pytest.mark.slow  # a whole residual-loop run: `pytest -m slow` (.ci/run runs it)
def test_a_delay_between_grid_points_is_fitted_with_its_gain_and_interval():
    data = delayed_pendulum(6, seed=1)
    base = nominal_model(NOMINAL, data)
    shooting_fit(base, data, 40, own_parameters(base), 15, False)  # g refit without the delay, as the trial's base
    # the screen's candidate: τ on the grid (2 samples) with its one-step gain
    start = fx.DelayedFeedback(-0.784, delay=2 * DT, target="omega").bind(["theta", "omega"])
    trial, fit = fit_with(base, start, data, 40, 15)
    values, interval = reported(trial.effects[-1], fit.values[:2], fit.stderr[:2])
    assert abs(values["delay"] - TAU) < 0.1 * TAU, values
    assert abs(values["coef"] - GAIN) < 0.1 * abs(GAIN), values
    for key in ("coef", "delay"):
        lo, hi = interval[key]
        assert lo < values[key] < hi and hi - lo < 0.1 * abs(values[key])
    assert trial.effects[-1].config()["delay"] == values["delay"]
    assert fitted_label("domega/dt: DelayedFeedback(omega, τ=0.1)", trial.effects[-1]) == (
        f"domega/dt: DelayedFeedback(omega, τ={values['delay']:.4g})"
    )


def test_a_window_reads_the_record_before_its_start_as_history():
    """A window started mid-record continues the whole-record rollout: the delayed term reads the recorded past
    (interpolated), not the window's first state held constant."""
    data = delayed_pendulum(2, seed=3).subset(slice(0, 2))
    effect = fx.DelayedFeedback(GAIN, delay=TAU, target="omega").bind(["theta", "omega"])
    model = nominal_model(NOMINAL, data, [effect])
    with torch.no_grad():
        ((_, whole),) = window_predictions(model, data, STEPS)  # [B, T, N, D] from t = 0
        sim = Trajectories(t=data.t, x=whole, edge_index=data.edge_index, meta=data.meta)
        windows = window_predictions(model, sim, 20)
    for s, pred in windows[1:]:  # the model's own solution, restarted from it every 20 steps
        assert torch.allclose(pred, whole[:, s : s + pred.shape[1]], atol=2e-4), s


def test_the_delay_stays_positive_and_carries_a_gradient():
    effect = fx.DelayedFeedback(0.5, delay=0.3, target="omega").bind(["theta", "omega"])
    assert math.isclose(effect.delay, 0.3) and effect.log_delay.requires_grad
    data = delayed_pendulum(1, seed=0)
    model = nominal_model(NOMINAL, data, [effect])
    _, pred = window_predictions(model, data, 10)[3]  # a window that starts mid-record: it reads the past too
    pred[:, -1, 0, 1].sum().backward()
    assert effect.log_delay.grad is not None and float(effect.log_delay.grad.abs()) > 0


def test_a_delay_fitted_past_the_records_is_no_finding():
    from mpsim.diagnose.trial import _beyond_record

    data = delayed_pendulum(1, seed=0)  # 5 s records
    long = fx.DelayedFeedback(0.1, delay=2.8e4, target="omega")  # scorecard a_damped: a fit ran off to 27 810 s
    assert "longer than the records" in _beyond_record(long, data)[0]
    assert _beyond_record(fx.DelayedFeedback(0.1, delay=TAU, target="omega"), data) == []
