"""`fixed.yaml` (issue 72, item 4): the spec with every carried effect written into its equations is the same model.

Oracle: the spec written by `written_spec` and read back as a plain `model=equations` spec (no effects) rolls out
exactly as the nominal spec carrying the effects does, on a driven oscillator with a term of every writable kind,
a drifting parameter and a dead zone followed by a saturation on its input; a delayed feedback is left out, with
the reason.
"""

from __future__ import annotations

import pytest
import torch
import yaml

from mpsim import effects as fx
from mpsim.diagnose.fixed import written_spec
from mpsim.models.equations import EquationsModel
from mpsim.solvers.odeint import ODESolver
from tests.diagnose.test_input_path import NOMINAL, _inputs, nominal, shaker


def _carrying(data):
    effects = [
        fx.LinearDamping(0.3, target="v"),
        fx.CubicStiffness(50.0, target="v", source="z"),
        fx.Bias(0.1, target="v"),
        fx.DryFriction(0.2, target="v", scale=0.05),
        fx.QuadraticDrag(0.4, target="v"),
        fx.PeriodicForcing(amplitude=0.5, omega=3.0, phase=0.2, target="v"),
        fx.ParameterDrift(param="k", rate=0.01, target="v"),
        fx.DeadZone("u", width=0.5, target="v"),
        fx.InputSaturation("u", limit=2.5, target="v"),
    ]
    return nominal(data, effects=effects)


def test_the_written_spec_rolls_out_as_the_model_with_its_effects():
    data = shaker([1.0, 1.0], seed=5).time_slice(0, 101)  # 2 s: the rollouts at a tight tolerance are slow
    model = _carrying(data)
    spec, left_out = written_spec(model)
    assert left_out == []
    spec = yaml.safe_load(yaml.safe_dump(spec))  # as fixed.yaml holds it
    plain = EquationsModel(2, 1, spec=spec, solver=ODESolver("dopri5", rtol=1e-9, atol=1e-11)).double()
    plain.bind_effects(data.state_names)
    plain.set_normalisation(model.state_mean, model.state_std)
    model.solver = ODESolver("dopri5", rtol=1e-9, atol=1e-11)
    want = model.rollout(data.x[:, 0], data.t, _inputs(data)).detach()
    got = plain.rollout(data.x[:, 0], data.t, _inputs(data)).detach()
    assert float((want - data.x).abs().max()) > 1e-2  # the effects matter here
    assert torch.allclose(got, want, atol=1e-7), float((got - want).abs().max())
    assert set(spec["learnable"]) >= {"k", "c", "linear_damping_v", "u_width", "u_limit", "k_drift"}
    assert spec["params"]["u_width"] == pytest.approx(0.5) and spec["params"]["m"] == NOMINAL["params"]["m"]


def test_a_delay_is_left_out_with_its_reason():
    data = shaker([1.0], seed=6)
    model = nominal(data, effects=[fx.DelayedFeedback(0.2, target="v", delay=0.1)])
    spec, left_out = written_spec(model)
    assert len(left_out) == 1 and "no form in the equations' grammar" in left_out[0]
    assert spec["equations"] == NOMINAL["equations"]
