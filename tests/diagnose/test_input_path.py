"""What reaches the system is not the input that was recorded (issue 71 item 7, issue 72 item 1): a shaker-driven
mass on a spring whose force is g_b·u in recording b (the DFKI pendulum's torque scale), or passes a dead zone, or
saturates.

The nominal model reads the force as recorded; the loop offers "InputGain(u, a gain per recording)" (its one-step
column on recording b's samples is ∂f/∂u·u), "DeadZone(u, width=w)" and "InputSaturation(u, limit=U)" (columns
∂f/∂u·δu on a grid of thresholds; the held-out fit moves the threshold) and must name the right one with its value,
a held-out recording's gain fitted on a warm-up window. Twins without the effect name nothing, and a cubic
stiffness is not named a saturation. The data come from a hand-written RK4 loop with the force held between
samples, not mpsim's simulator.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mpsim import effects as fx
from mpsim.data.trajectories import Inputs, Trajectories
from mpsim.diagnose.heldout import EFFECTS_NAMED, judge
from mpsim.diagnose.library import Candidate
from mpsim.diagnose.loop import screen
from mpsim.diagnose.nuisance import input_candidates
from mpsim.diagnose.params import DiagnoseParams
from mpsim.diagnose.perrecord import gains_text
from mpsim.diagnose.shooting import window_error
from mpsim.errors import ConfigError
from mpsim.models.equations import EquationsModel
from mpsim.solvers.odeint import ODESolver

M, K, C = 0.5, 20.0, 0.4  # mass (weighed: fixed), stiffness, damping
H, EVERY, STEPS = 0.002, 10, 300  # RK4 step, logged every 10th: dt = 0.02, 6 s records
NOMINAL = {
    "states": ["z", "v"],
    "inputs": ["u"],
    "equations": {"z": "v", "v": "(u - k*z - c*v)/m"},
    "params": {"k": K, "c": C, "m": M},
    "learnable": ["k", "c"],
    "kinematic": ["z"],
    "nodes": 1,
}


def shaker(gains: list[float], seed: int, actuator=None, cubic: float = 0.0) -> Trajectories:
    """z' = v, m v' = F − k z − c v − cubic·z³: recording b's shaker force F = actuator(g_b·u) (default: g_b·u), u
    a sum of five sines (0.5–4 Hz, random phases) held between samples; hand-written RK4 vectorised over
    recordings, logged every 10th step."""
    rng = np.random.default_rng(seed)
    n, g = len(gains), np.asarray(gains)
    freq = rng.uniform(0.5, 4.0, (n, 5))
    phase = rng.uniform(0, 2 * np.pi, (n, 5))
    t_log = np.arange(STEPS + 1) * H * EVERY
    u = np.sin(2 * np.pi * freq[:, None, :] * t_log[None, :, None] + phase[:, None, :]).sum(-1)  # [n, T]
    y = np.zeros((n, 2))
    x = np.empty((n, STEPS + 1, 2))
    for s in range(STEPS * EVERY + 1):  # the generator's time loop
        if s % EVERY == 0:
            x[:, s // EVERY] = y
        if s == STEPS * EVERY:
            break
        force = g * u[:, s // EVERY]  # zero-order hold over the logging interval
        force = force if actuator is None else actuator(force)
        k1 = _field(y, force, cubic)
        k2 = _field(y + 0.5 * H * k1, force, cubic)
        k3 = _field(y + 0.5 * H * k2, force, cubic)
        k4 = _field(y + H * k3, force, cubic)
        y = y + H / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return Trajectories(
        t=torch.as_tensor(t_log),
        x=torch.as_tensor(x)[:, :, None, :],
        edge_index=torch.zeros(2, 0, dtype=torch.long),
        u=torch.as_tensor(u)[:, :, None, None],
        meta={"state_names": ["z", "v"], "control_names": ["u"], "input_hold": "zoh", "source": "shaker.csv"},
    )


def _field(y: np.ndarray, force: np.ndarray, cubic: float) -> np.ndarray:  # y: [n, 2], force: [n]
    return np.stack([y[:, 1], (force - K * y[:, 0] - C * y[:, 1] - cubic * y[:, 0] ** 3) / M], axis=1)


def dead_zone(w: float):
    return lambda f: np.sign(f) * np.maximum(np.abs(f) - w, 0.0)


def saturation(limit: float):
    return lambda f: np.clip(f, -limit, limit)


def nominal(train: Trajectories, effects=()) -> EquationsModel:
    """The shaker as the scientist writes it: the force as recorded, m weighed (fixed)."""
    solver = ODESolver("dopri5", rtol=1e-7, atol=1e-9)
    model = EquationsModel(2, 1, spec=NOMINAL, effects=list(effects), solver=solver).double()
    model.bind_effects(train.state_names)
    flat = train.x.reshape(-1, 2)
    model.set_normalisation(flat.mean(0), flat.std(0))
    return model


def _inputs(data: Trajectories) -> Inputs:
    return Inputs(edge_index=data.edge_index, u=data.u, meta=data.meta)


def test_the_gain_column_is_the_input_term_on_its_own_recording():
    data = shaker([1.0, 1.0, 1.0], seed=1)
    (cand,) = input_candidates(nominal(data), data, ("InputGain",))
    assert (cand.kind, cand.params, cand.per_row) == ("InputGain", {"input": "u"}, True)
    assert cand.label(data.state_names, 1) == "dv/dt: InputGain(u, a gain per recording)"
    assert tuple(cand.basis.shape) == (3, STEPS, 1, 2, 3)  # one column per recording
    term = data.u[:, :-1, :, 0] / M  # [B, T-1, N] ∂f_v/∂u·u, the force held over each step
    for b in range(3):
        assert torch.allclose(cand.row(1)[b, ..., b], term[b], atol=1e-12)
        others = [j for j in range(3) if j != b]
        assert float(cand.row(1)[b][..., others].abs().max()) == 0.0  # recording b's samples: b's column only
    assert float(cand.row(0).abs().max()) == 0.0  # ż = v reads no input
    assert input_candidates(nominal(data), data, ("LinearDamping",)) == []  # only when asked for
    assert input_candidates(nominal(data), data.subset([0]), ("InputGain",)) == []  # one recording: no finding


def test_the_gains_round_trip_through_their_config_and_the_model_applies_them():
    gains = [0.8, 1.0, 1.25]
    data = shaker(gains, seed=2)
    cand = Candidate("InputGain", None, {"input": "u"}, per_row=True)
    cfg = cand.effect_config([g - 1 for g in gains], 1, data.state_names)
    assert cfg["_target_"] == "mpsim.effects.InputGain" and cfg["input"] == "u"
    assert cfg["gains"] == pytest.approx(gains)
    effect = cand.make_effect([g - 1 for g in gains], 1, data.state_names)
    rebuilt = fx.InputGain(**{k: v for k, v in effect.config().items() if k != "_target_"})
    assert rebuilt.gains == pytest.approx(gains) and rebuilt.per_record and not rebuilt.uses_time
    model = nominal(data, effects=[rebuilt])
    assert model.terms() == [] and model.input_gains() == [rebuilt]
    pred = model.rollout(data.x[:, 0], data.t, _inputs(data)).detach()
    assert float((pred - data.x).abs().max()) < 1e-5  # each recording with its own gain reproduces the generator
    plain = nominal(data).rollout(data.x[:, 0], data.t, _inputs(data)).detach()
    assert float((plain - data.x)[0].abs().max()) > 100 * float((pred - data.x).abs().max())  # and without: not
    steps = model.one_step(data.x, data.t, _inputs(data)).detach()  # one batch of every step: rows say their record
    assert float((steps - data.x[:, 1:]).abs().max()) < 1e-6
    assert model.time_invariant  # windows batch window-major, each row told its recording
    assert float(window_error(model, data, 30).max()) < 1e-8
    assert float(window_error(nominal(data), data, 30).max()) > 1e-4
    with pytest.raises(ConfigError, match="only model=equations"):
        rebuilt(data.t[0], data.x[:, 0], None)  # a system or another model cannot carry it
    with pytest.raises(ConfigError, match="not an input of the model"):
        nominal(data, effects=[fx.InputGain("tau", gains)])


PARAMS = {
    "kinds": ["LinearDamping", "CubicStiffness", "Bias", "InputGain", "DeadZone", "InputSaturation"],
    "n_boot": 20,
    "horizon": 60,
    "shooting_iters": 15,
}
GAINS = [0.8, 1.15, 0.9, 1.25, 1.05, 0.85, 1.2, 0.95, 1.1, 0.75, 1.3, 0.9]


def _loop(gains: list[float], sigma: float = 0.002, actuator=None, cubic: float = 0.0):
    data = shaker(gains, seed=0, actuator=actuator, cubic=cubic)
    gen = torch.Generator().manual_seed(3)
    data.x = data.x + sigma * torch.randn(data.x.shape, generator=gen, dtype=torch.float64)  # sensor noise
    train, test = data.subset(slice(0, 8)), data.subset(slice(8, 12))
    params = DiagnoseParams(**PARAMS)
    model = nominal(train)
    diag, library = screen(model, train, params, 0)
    return judge(model, diag, library, train, test, params)


@pytest.mark.slow  # a whole residual-loop run: `pytest -m slow` (.ci/run runs it)
def test_a_force_scaled_in_every_recording_is_named_an_input_gain_with_its_gains():
    j = _loop(GAINS)
    assert j.verdict == EFFECTS_NAMED, (j.verdict, [(t.label, t.reason) for t in j.trials])
    (gain,) = j.named
    assert gain.kind == "InputGain" and gain.effect["input"] == "u"
    assert gain.effect["gains"] == pytest.approx(GAINS[:8], rel=0.1)
    assert gain.values["gain min"] == pytest.approx(min(GAINS[:8]), rel=0.1)


@pytest.mark.slow
def test_the_same_force_in_every_recording_names_nothing():
    j = _loop([1.0] * 12)
    assert j.named == [], [(t.label, t.reason) for t in j.named]


def test_a_dead_zone_and_a_saturation_shape_the_input_the_model_reads():
    data = shaker([1.0, 1.0], seed=4, actuator=dead_zone(0.6))
    model = nominal(data, effects=[fx.DeadZone("u", width=0.6)])
    assert model.time_invariant and model.terms() == []
    pred = model.rollout(data.x[:, 0], data.t, _inputs(data)).detach()
    assert float((pred - data.x).abs().max()) < 1e-5  # the dead zone of the generator, through the model's input
    sat = fx.InputSaturation("u", limit=1.5)
    v = torch.tensor([[-3.0], [-1.0], [0.5], [2.0]], dtype=torch.float64)[..., None]  # [M, N, C]
    assert sat.through(v, 0).flatten().tolist() == [-1.5, -1.0, 0.5, 1.5]
    assert fx.DeadZone("u", width=0.6).through(v, 0).flatten().tolist() == pytest.approx([-2.4, -0.4, 0.0, 1.4])
    rebuilt = fx.InputSaturation(**{k: v for k, v in sat.config().items() if k != "_target_"})
    assert rebuilt.threshold == pytest.approx(1.5) and rebuilt.config()["limit"] == pytest.approx(1.5)
    with pytest.raises(ConfigError, match="must be > 0"):
        fx.DeadZone("u", width=0.0)
    cands = input_candidates(nominal(data), data, ("DeadZone", "InputSaturation"))
    size = data.u.abs().flatten()
    widths = [c.params["width"] for c in cands if c.kind == "DeadZone"]
    assert widths == sorted(float(torch.quantile(size, q)) for q in (0.05, 0.1, 0.2, 0.35))
    dz = next(c for c in cands if c.kind == "DeadZone")
    w = dz.params["width"]
    want = -data.u[:, :-1, :, 0].clamp(-w, w) / M  # ∂f_v/∂u·δu with δu = −clip(u, −w, w), held over each step
    assert torch.allclose(dz.row(1)[..., 0], want, atol=1e-12)
    assert dz.label(data.state_names, 1) == f"dv/dt: DeadZone(u, width={w:.4g})"


@pytest.mark.slow
def test_a_dead_zone_on_the_force_is_named_with_its_width():
    j = _loop([1.0] * 12, actuator=dead_zone(0.6))
    assert j.verdict == EFFECTS_NAMED, (j.verdict, [(t.label, t.reason) for t in j.trials])
    (dz,) = j.named
    assert dz.kind == "DeadZone" and dz.values["width"] == pytest.approx(0.6, rel=0.1)


@pytest.mark.slow
def test_a_saturating_force_is_named_with_its_limit():
    j = _loop([1.0] * 12, actuator=saturation(2.0))
    assert j.verdict == EFFECTS_NAMED, (j.verdict, [(t.label, t.reason) for t in j.trials])
    (sat,) = j.named
    assert sat.kind == "InputSaturation" and sat.values["limit"] == pytest.approx(2.0, rel=0.1)


@pytest.mark.slow
def test_a_cubic_stiffness_is_not_named_a_saturation():
    j = _loop([1.0] * 12, cubic=100.0)
    assert [t.kind for t in j.named] == ["CubicStiffness"], [(t.label, t.reason) for t in j.trials]


def test_gains_that_agree_are_said_to_be_one_gain_of_the_input():
    agree = gains_text([-0.2, -0.2001, -0.1999], [0.01, 0.01, 0.01])
    assert "mean 0.8" in agree and "one gain for every record" in agree
    spread = gains_text([-0.2, 0.2, 0.0], [0.01, 0.01, 0.01])
    assert "spread (sd) 0.2" in spread and "one gain" not in spread
