"""PySINDy's extended library in `mpsim bench bench=peers` (issue 61): each new kind of column, on a known answer.

Each test puts one term into a synthetic residual and checks that the sparse fit names it alone, under the name
the scorecard judges (t-modulated state, DelayedFeedback on the grid, ParameterDrift, SineCoupling(k=2)), with
its coefficient."""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from mpsim.bench.peers import CASES, PeerCase, PeersBench, judge, kind_of
from mpsim.bench.peers_cases import TODO
from mpsim.bench.peers_library import Column, row_columns, sparse_fit, state_columns, timed_columns
from mpsim.models.equations import EquationsModel
from mpsim.spec.files import load_spec_file
from mpsim.systems.equations import EquationsSystem
from mpsim.systems.simulation import simulate

SPECS = Path(__file__).resolve().parents[2] / "examples" / "diagnose_cases"
PENDULUM = {
    "states": ["theta", "omega"],
    "equations": {"theta": "omega", "omega": "-(g/l)*sin(theta)"},
    "params": {"g": 9.81, "l": 1.0},
    "learnable": ["g"],
    "nodes": 1,
}


@pytest.fixture(scope="module")
def pendulum():
    truth = {**PENDULUM, "init": {"theta": [-2.0, 2.0], "omega": [-1.0, 1.0]}, "dt": 0.1, "horizon": 100}
    return simulate(EquationsSystem(spec=truth), 6, seed=0)


@pytest.fixture(scope="module")
def ring():
    spec = {**load_spec_file(SPECS / "f_kuramoto_harm2_data.yaml"), "horizon": 80}
    return simulate(EquationsSystem(spec=spec), 3, seed=0)


def fit(columns, residual, row="omega", first=0):  # residual: [B, T - first, N] the row's synthetic residual
    ps = pytest.importorskip("pysindy")
    kept = [Column(c.kind, c.name, c.params, c.values[:, first:]) for c in columns]
    return sparse_fit(ps, kept, residual.reshape(-1), 0.01 * float(np.sqrt((residual**2).mean())), row)


def by_name(columns, name):
    return next(c for c in columns if c.name == name).values[..., 0]  # [B, T, N]


def test_a_t_modulated_state_is_recovered_with_its_coefficient(pendulum):
    shared = state_columns(pendulum)
    t = pendulum.t.double().numpy()[None, :, None]
    residual = 0.3 * t * pendulum.x[..., 0].double().numpy()  # 0.3·t·θ = −0.3 × the column t·(−θ)
    named = fit(shared + timed_columns(pendulum, shared), residual)
    assert [(e["kind"], e["label"]) for e in named] == [("t·LinearDamping", "domega/dt: t·LinearDamping(theta)")]
    assert named[0]["values"]["coef"] == pytest.approx(-0.3, rel=1e-6)


def test_a_delayed_copy_at_two_steps_is_named_delayed_feedback_with_its_grid_delay(pendulum):
    # states without memory (white noise): on smooth records the copies s(t − m·dt) are nearly collinear and
    # STLSQ's ridge spreads a delay over them; the bench shows that, this test checks the column itself
    g = torch.Generator().manual_seed(0)
    noise = replace(pendulum, x=torch.randn(pendulum.x.shape, generator=g, dtype=torch.float64))
    shared = state_columns(noise)
    residual = -0.5 * np.roll(noise.x[..., 1].numpy(), 2, axis=1)  # −0.5·ω(t − 2·dt)
    named = fit(shared, residual[:, 2:], first=2)
    assert [e["kind"] for e in named] == ["DelayedFeedback"], named
    assert named[0]["values"]["coef"] == pytest.approx(-0.5, rel=1e-6)
    assert named[0]["values"]["delay"] == pytest.approx(0.2)


def test_a_t_modulated_nominal_term_is_named_parameter_drift_with_its_rate(pendulum):
    model = EquationsModel(2, spec=PENDULUM)
    rhs = np.zeros(pendulum.x.shape)
    columns = state_columns(pendulum) + row_columns(model, pendulum, 1, 1.0, rhs)
    t = pendulum.t.double().numpy()[None, :, None]
    residual = 0.02 * t * -9.81 * np.sin(pendulum.x[..., 0].double().numpy())  # g·(1 + 0.02·t)
    named = fit(columns, residual)
    assert [(e["kind"], e["label"]) for e in named] == [("ParameterDrift", "domega/dt: ParameterDrift(g)")]
    assert named[0]["values"]["s"] == pytest.approx(0.02, rel=1e-4)


def test_a_second_harmonic_column_is_named_sine_coupling_k2(ring):
    shared = state_columns(ring)
    assert {"SineCoupling(k=2)", "SineCoupling(k=3)", "CosineCoupling(k=2)"} <= {c.kind for c in shared}
    residual = 0.25 * by_name(shared, "SineCoupling(theta, k=2)")
    named = fit(shared, residual, row="theta")
    assert [(e["kind"], e["label"]) for e in named] == [("SineCoupling(k=2)", "dtheta/dt: SineCoupling(theta, k=2)")]
    assert named[0]["values"]["coef"] == pytest.approx(0.25, rel=1e-6)


def test_new_kinds_are_judged_by_their_value_and_mpsim_names_carry_the_harmonic():
    delay = PeerCase("g", "[]", ("DelayedFeedback", "v", "delay", 0.15, 0.10))
    named = [{"kind": "DelayedFeedback", "row": "v", "values": {"coef": -0.4, "delay": 0.16}}]
    assert judge(delay, named) == (True, "6.67%")
    assert judge(delay, [{**named[0], "values": {"coef": -0.4, "delay": 0.2}}])[0] is False
    assert kind_of({"kind": "SineCoupling", "effect": {"harmonic": 2}}) == "SineCoupling(k=2)"
    assert kind_of({"kind": "SineCoupling", "effect": {"coef": 0.25}}) == "SineCoupling"
    assert CASES["f_kuramoto_harm2"].text == "SineCoupling(theta, k=2) coef 0.25"


def test_a_case_without_specs_or_with_a_todo_truth_gets_a_row_that_says_so(tmp_path, monkeypatch):
    pytest.importorskip("pysindy")
    for name in ("a_chain_data.yaml", "a_chain_model.yaml"):
        shutil.copy(SPECS / name, tmp_path / name)
    # a case whose specs are there but whose truth is still TODO, and one whose specs are not
    monkeypatch.setitem(CASES, "x_todo", PeerCase("a_chain", "[]", ("LinearDamping", "v", "coef", TODO, 0.10)))
    monkeypatch.setitem(CASES, "x_nospec", PeerCase("x_nospec"))
    rows = PeersBench(cases=["a_undamped", "x_todo", "x_nospec"], twins=False, specs=str(tmp_path)).run()
    texts = {r["case"]: r["PySINDy named (fitted)"] for r in rows}
    assert texts["x_nospec"] == "spec missing: x_nospec_data.yaml, x_nospec_model.yaml"
    assert texts["x_todo"].startswith("truth TODO") and CASES["x_todo"].todo
    assert rows[0]["PySINDy right"] in ("yes", "NO")
