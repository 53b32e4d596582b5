"""Latent states of any kind, estimated through the model (`mpsim.models.latent`): an upper tank's level from the
lower one, a velocity a derivative cannot follow (8.6 samples a period), every state of a belt drive read as
|speed|. The data come from generators of our own (`cli/latent_cases.py`: numpy RK4 at 20 steps a sample, noise,
quantisation); the model is the generator's own equations, so the estimate can be checked against the truth."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from mpsim.data.pipeline import DataOptions, load_splits
from mpsim.models.equations import EquationsModel
from mpsim.models.latent import estimate_pending
from mpsim.spec import load_spec_file

_spec = importlib.util.spec_from_file_location("latent_cases", Path(__file__).parents[2] / "cli" / "latent_cases.py")
assert _spec is not None and _spec.loader is not None
cases = importlib.util.module_from_spec(_spec)
sys.modules["latent_cases"] = cases  # dataclasses look their module up
_spec.loader.exec_module(cases)


def _estimated(tmp_path: Path, name: str, observed: str, hold: str, rows: int, segment: float):
    """(the test split with its latent states estimated, the truth, the case's info) of case `name`'s first rows."""
    info = cases.write_case(tmp_path, name)
    spec = load_spec_file(tmp_path / name / "model.yaml")
    model = EquationsModel(len(spec.get("states")) + len(spec.get("outputs") or {}), control_dim=1, spec=spec).double()
    names = [*spec["states"], *(spec.get("outputs") or {})]
    model.bind_inputs(["u"])
    model.bind_effects(names)
    rates = model.spec.rates()
    options = DataOptions(
        path=str(tmp_path / name / f"{name}.csv"),
        observed=[observed],
        input_hold=hold,
        train_range=[0, rows // 2],
        val_range=[0, rows // 2],
        test_range=[rows // 2, rows],
        segment=segment,
    )
    splits = load_splits(
        options, tmp_path, "float64", states=names, rates=rates, inputs=["u"], outputs=list(spec.get("outputs") or {})
    )
    truth = np.load(tmp_path / name / "truth.npz")
    return splits.test, estimate_pending(model, splits.test), truth, info


def _rmse_share(data, truth, info, state: str) -> float:
    """RMSE of the estimated `state` against the truth, over its spread."""
    i, j = data.state_names.index(state), info["states"].index(state)
    errs = []
    for b, entry in enumerate(data.meta["segments"]):
        want = np.interp(entry["t0"] + data.t.numpy(), truth["t"], truth["x"][:, j])
        errs.append(data.x[b, :, 0, i].numpy() - want)
    return float(np.sqrt(np.mean(np.concatenate(errs) ** 2))) / info["spread"][state]


@pytest.mark.slow  # 3–6 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_the_upper_tank_is_estimated_from_the_lower_one(tmp_path):
    before, after, truth, info = _estimated(tmp_path, "tanks", "h2", "zoh", 400, 200.0)
    assert before.meta["pending"] == ["h1"] and "pending" not in after.meta
    assert _rmse_share(after, truth, info, "h1") < 0.1  # 3.8 % in cli/latent_cases.sh's longer run
    assert after.meta["estimated"]["h1"].startswith("unscented Kalman smoother over the nominal model")


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_a_velocity_at_8_6_samples_a_period_is_left_to_the_model_and_beats_the_derivative(tmp_path):
    before, after, truth, info = _estimated(tmp_path, "oscillator", "q", "linear", 300, 5.0)
    assert before.meta["pending"] == ["v"] and "gain of 0.7" in before.meta["pending_why"]["v"]
    share = _rmse_share(after, truth, info, "v")
    assert share < 0.05, share
    q = before.x[..., 0].double()  # the 5-sample Savitzky-Golay derivative it replaced
    from mpsim.data.latent import savgol_derivative

    sg = before.__class__(t=before.t, x=torch.stack([q, savgol_derivative(q, float(before.t[1]), 5)], -1),
                          edge_index=before.edge_index, meta=before.meta)  # fmt: skip
    assert share < 0.5 * _rmse_share(sg, truth, info, "v")


@pytest.mark.slow  # ~20 s: 3 states, the unscented smoother at several noise scales
def test_every_state_of_a_belt_drive_read_as_its_absolute_speed(tmp_path):
    before, after, truth, info = _estimated(tmp_path, "abs_speed", "y", "zoh", 600, 1.0)
    assert sorted(before.meta["pending"]) == ["d", "r", "s"]
    for state in ("d", "s"):
        assert _rmse_share(after, truth, info, state) < 0.05, state
