"""A parameter that drifts (issue 61, item 7): a spring whose stiffness grows linearly in time.

The nominal model has k learnable but constant; the loop offers "k drifts: k·(1 + s·t)" (its one-step column is
t·k·∂f/∂k) and must name it with the rate s, judged on held-out records like any other candidate. A clean twin names
nothing. The data come from a hand-written RK4 loop, not mpsim's simulator.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mpsim import effects as fx
from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.heldout import EFFECTS_NAMED, judge
from mpsim.diagnose.library import Candidate
from mpsim.diagnose.loop import screen
from mpsim.diagnose.nuisance import drift_candidates, model_sensitivities
from mpsim.diagnose.params import DiagnoseParams
from mpsim.models.equations import EquationsModel
from tests.diagnose.white_box import nominal_model

K0, C, RATE = 4.0, 0.1, 0.05  # stiffness at t = 0, damping, relative drift of k per unit time
H, EVERY, STEPS = 0.005, 10, 200  # RK4 step, logged every 10th: dt = 0.05, 10 s records
NOMINAL = {
    "states": ["z", "v"],
    "equations": {"z": "v", "v": "-k*z - c*v"},
    "params": {"k": K0, "c": C},
    "learnable": ["k"],
    "kinematic": ["z"],
    "nodes": 1,
}


def spring(n: int, seed: int, rate: float) -> Trajectories:
    """z' = v, v' = −k(t) z − c v with k(t) = K0·(1 + rate·t) (t from 0 in every recording), stepped by a
    hand-written RK4 vectorised over recordings, logged every 10th step."""
    rng = np.random.default_rng(seed)
    y = np.stack([rng.uniform(-1.0, 1.0, n), rng.uniform(-1.0, 1.0, n)], axis=1)  # [n, 2]

    def f(t: float, y: np.ndarray) -> np.ndarray:  # y: [n, 2]
        return np.stack([y[:, 1], -K0 * (1 + rate * t) * y[:, 0] - C * y[:, 1]], axis=1)

    x = np.empty((n, STEPS + 1, 2))
    for s in range(STEPS * EVERY + 1):  # the generator's time loop
        t = s * H
        if s % EVERY == 0:
            x[:, s // EVERY] = y
        k1 = f(t, y)
        k2 = f(t + 0.5 * H, y + 0.5 * H * k1)
        k3 = f(t + 0.5 * H, y + 0.5 * H * k2)
        k4 = f(t + H, y + H * k3)
        y = y + H / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return Trajectories(
        t=torch.arange(STEPS + 1, dtype=torch.float64) * H * EVERY,
        x=torch.as_tensor(x)[:, :, None, :],
        edge_index=torch.zeros(2, 0, dtype=torch.long),
        meta={"state_names": ["z", "v"], "source": "spring.csv"},
    )


def nominal(train: Trajectories, effects=()) -> EquationsModel:
    """The spring as the scientist writes it: k learnable and constant."""
    return nominal_model(NOMINAL, train, effects)


def test_the_drift_column_is_t_times_p_times_the_sensitivity():
    data = spring(3, seed=1, rate=0.0)
    model = nominal(data)
    (cand,) = drift_candidates(model, data, ("ParameterDrift",))  # k only: c is fixed
    assert (cand.kind, cand.params, cand.per_row) == ("ParameterDrift", {"param": "k"}, True)
    assert cand.label(data.state_names, 1) == "dv/dt: ParameterDrift(k)"
    x, t = data.x.double(), data.t.double()
    col = t[None, :, None] * K0 * (-x[..., 0])  # [B, T, N] t·k·∂f_v/∂k = −t·k·z
    want = 0.5 * (col[:, 1:] + col[:, :-1])
    assert torch.allclose(cand.row(1)[..., 0], want, atol=1e-12)
    assert float(cand.row(0).abs().max()) == 0.0  # ż = v does not read k
    sens = model_sensitivities(model, data)  # [B, T-1, N, D, 1]
    assert sens is not None and sens.shape == cand.basis.shape
    assert drift_candidates(model, data, ("LinearDamping",)) == []  # only when the kind is asked for


def test_a_drift_round_trips_through_its_config_and_the_model_applies_it():
    data = spring(2, seed=2, rate=RATE)
    cand = Candidate("ParameterDrift", None, {"param": "k"}, per_row=True)
    cfg = cand.effect_config([RATE], 1, data.state_names)
    assert cfg == {"_target_": "mpsim.effects.ParameterDrift", "target": "v", "param": "k", "rate": RATE}
    effect = cand.make_effect([RATE], 1, data.state_names)
    assert effect.uses_time and effect.config() == cfg
    assert effect.describe() == "k drifts: k·(1 + s·t), s = 0.05"
    rebuilt = fx.ParameterDrift(**{k: v for k, v in effect.config().items() if k != "_target_"})
    assert rebuilt.config() == cfg
    model = nominal(data, effects=[rebuilt])
    assert not model.time_invariant
    from mpsim.data.trajectories import Inputs

    pred = model.rollout(data.x[:, 0], data.t, Inputs(edge_index=data.edge_index, meta=data.meta))
    err = float((pred.detach() - data.x).abs().max())
    assert err < 1e-4, err  # the drifting model reproduces the generator
    steps = model.one_step(data.x, data.t, Inputs(edge_index=data.edge_index, meta=data.meta))
    assert float((steps.detach() - data.x[:, 1:]).abs().max()) < 1e-6  # absolute time in the batched one-step too
    with pytest.raises(Exception, match="only model=equations"):
        rebuilt(data.t[0], data.x[:, 0], None)  # a system or another model cannot carry it


PARAMS = {
    "kinds": ["LinearDamping", "CubicStiffness", "ParameterDrift"],
    "n_boot": 20,
    "fit_trajectories": 6,
    "horizon": 40,
    "shooting_iters": 15,
}


def _loop(rate: float, sigma: float = 0.01):
    data = spring(20, seed=0, rate=rate)
    gen = torch.Generator().manual_seed(3)
    data.x = data.x + sigma * torch.randn(data.x.shape, generator=gen, dtype=torch.float64)  # measurement noise
    train, test = data.subset(slice(0, 12)), data.subset(slice(14, 20))
    params = DiagnoseParams(**PARAMS)
    model = nominal(train)
    diag, library = screen(model, train, params, 0)
    return diag, judge(model, diag, library, train, test, params)


@pytest.mark.slow  # a whole residual-loop run: `pytest -m slow` (.ci/run runs it)
def test_a_stiffness_that_grows_linearly_is_named_a_drift_with_its_rate():
    diag, j = _loop(RATE)
    assert j.verdict == EFFECTS_NAMED, (j.verdict, [(t.label, t.reason) for t in j.trials])
    (drift,) = j.named
    assert drift.kind == "ParameterDrift" and drift.effect["param"] == "k"
    assert drift.effect["rate"] == pytest.approx(RATE, rel=0.1)
    assert drift.values["s"] == pytest.approx(RATE, rel=0.1)
    assert j.model is not None and any(getattr(e, "param", None) == "k" for e in j.model.effects)


def test_a_spring_without_drift_names_nothing():
    diag, j = _loop(0.0)
    assert j.named == [], [(t.label, t.reason) for t in j.named]
