"""cli/measured_cases.py, issue 60's measured-style cases from generators of our own (numpy RK4 at a fine fixed
step, the input held zero-order): each written spec parses, and mpsim's equations model with the TRUE parameters
(and the missing effect added: its mpsim effect class, or the truth written as equations where mpsim has none)
reproduces the generator's trajectory from the recorded input to within the discretisation error (a check of the
specs' units and of truth.json's coefficients, not of the residual loop). Short recordings keep it fast."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from mpsim.data.trajectories import Inputs
from mpsim.data.wide import read_wide_csv
from mpsim.effects import CubicStiffness, DryFriction
from mpsim.models.equations import EquationsModel
from mpsim.solvers.odeint import ODESolver
from mpsim.spec import load_spec_file

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("measured_cases", ROOT / "cli" / "measured_cases.py")
mc = importlib.util.module_from_spec(_spec)
sys.modules["measured_cases"] = mc  # dataclasses look their module up
_spec.loader.exec_module(mc)

SECONDS = {"b_axis_coulomb": 1.0, "c_duffing": 2.0, "d_input_gain": 2.0, "d_deadzone": 1.0}
NONE = torch.zeros(2, 0, dtype=torch.long)


def _truth_model(name: str, spec: dict, truth: dict) -> tuple[dict, list]:
    """The spec with the true nominal parameters, and the missing effect: an mpsim effect, or (no such kind) the
    truth written into the equations."""
    spec = {**spec, "params": dict(truth["nominal_true"])}
    missing = truth["missing_effect"]
    if missing["kind"] == "DryFriction":
        eps = missing["physical"]["eps_m_per_s"]
        return spec, [DryFriction(missing["coef"], target=missing["target"], source=missing["source"], scale=eps)]
    if missing["kind"] == "CubicStiffness":
        return spec, [CubicStiffness(missing["coef"], target=missing["target"], source=missing["source"])]
    if name == "d_input_gain":  # the actuator delivers g·u
        v = "(g*u - c*v - k*q)/m"
        return {
            **spec,
            "equations": {"q": "v", "v": v},
            "params": {**spec["params"], "g": missing["physical"]["gain"]},
        }, []
    assert name == "d_deadzone"  # sign(u)·max(|u| − d, 0), u held constant over each sample interval
    v = "((u - d*sign(u))*(sign(abs(u) - d) + 1)/2 - Fv*v)/m"
    return {
        **spec,
        "equations": {"q": "v", "v": v},
        "params": {**spec["params"], "d": missing["physical"]["deadzone_N"]},
    }, []


def _rollout(spec: dict, effects: list, rec) -> np.ndarray:
    """[T, 2] mpsim's dopri5 rollout of `spec` from the recording's true first state, driven by its recorded input."""
    model = EquationsModel(2, 1, spec=spec, effects=effects, solver=ODESolver("dopri5", rtol=1e-9, atol=1e-12))
    model = model.double()
    model.bind_effects(["q", "v"])
    model.bind_inputs(["u"])
    u = torch.tensor(rec.u)[None, :, None, None]
    x0 = torch.tensor(rec.x[0])[None, None, :]
    with torch.no_grad():
        out = model.rollout(
            x0, torch.tensor(rec.t), Inputs(NONE, u, None, {"input_hold": "zoh", "control_names": ["u"]})
        )
    return out[0, :, 0].numpy()


@pytest.mark.slow  # long; outside the default suite (<4 min on 2 cores), run by .ci/run's -m slow step
@pytest.mark.parametrize("name", list(mc.CASES))
def test_mpsim_with_the_true_parameters_follows_the_generator(name, tmp_path):
    truth = mc.write_case(tmp_path, name, seed=0, seconds=SECONDS[name])
    spec = load_spec_file(tmp_path / name / "model.yaml")  # parses (and is the spec the recipe trains)
    assert spec["inputs"] == ["u"] and spec["states"] == ["q", "v"]
    assert json.loads((tmp_path / name / "truth.json").read_text()) == truth
    for p in spec["learnable"]:  # initial guesses a few % off
        assert 0.01 <= abs(spec["params"][p] / truth["nominal_true"][p] - 1) <= 0.06, p
    made = mc.make_case(name, seed=0, seconds=SECONDS[name])
    rec, clean = made["recording"], made["clean"]
    with_effect = _rollout(*_truth_model(name, spec, truth), rec)
    without = _rollout({**spec, "params": dict(truth["nominal_true"])}, [], rec)
    dev = np.abs(with_effect - rec.x).max(0)
    # RK4 at dt/substeps against dopri5 at rtol 1e-9: agreement to far below one sensor count (measured: ≤ 1e-10 m)
    assert dev[0] < 1e-8 and dev[1] < 1e-6, dev
    # ... while the nominal model without the missing effect, true parameters, drifts far away (the effect matters)
    assert np.abs(without - rec.x).max(0)[0] > 1e3 * truth["sensor"]["quantum_m"]
    # the clean twin is the nominal model itself
    assert np.abs(_rollout({**spec, "params": dict(truth["nominal_true"])}, [], clean) - clean.x).max(0)[0] < 1e-8


@pytest.mark.parametrize("name", list(mc.CASES))
def test_the_csv_reads_back_as_the_recording(name, tmp_path):
    truth = mc.write_case(tmp_path, name, seed=0, seconds=0.5)
    rec = mc.make_case(name, seed=0, seconds=0.5)["recording"]
    cols = truth["columns"]
    for file, want in ((truth["recording"], rec),):
        table = read_wide_csv(
            tmp_path / name / file, time_column=cols["time"], dt=None if cols["time"] else truth["dt"]
        )
        assert np.allclose(table.columns[cols["q"]], want.y, atol=1e-12)
        assert np.allclose(table.columns["u"], want.u, atol=1e-12)
        assert (table.t is None and cols["time"] is None) or np.allclose(table.t, want.t)
    # the sensor: quantised to its step
    assert np.allclose(np.round(rec.y / truth["sensor"]["quantum_m"]) * truth["sensor"]["quantum_m"], rec.y, atol=1e-15)


@pytest.mark.slow  # 3–6 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_cases_are_deterministic_and_sized_as_stated(tmp_path):
    for name in mc.CASES:  # the missing term: a few % to ~20 % of dv/dt (RMS), full length
        assert 0.03 < mc.make_case(name)["info"]["share_of_dvdt_rms"] < 0.22, name
    a = mc.make_case("c_duffing", seed=3, seconds=1.0)
    b = mc.make_case("c_duffing", seed=3, seconds=1.0)
    assert np.array_equal(a["recording"].y, b["recording"].y) and np.array_equal(a["recording"].u, b["recording"].u)
    assert not np.array_equal(a["recording"].u, mc.make_case("c_duffing", seed=4, seconds=1.0)["recording"].u)
    # the twin shares the excitation and the noise draws: only the missing effect differs
    assert np.array_equal(a["recording"].u, a["clean"].u)
    mc.main([str(tmp_path), "--seconds", "0.2", "--cases", "b_axis_coulomb,d_input_gain"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b_axis_coulomb", "d_input_gain"]
    header = (tmp_path / "b_axis_coulomb" / "b_axis_coulomb.csv").read_text().splitlines()[0]
    assert header == "t,enc_pos,u"
