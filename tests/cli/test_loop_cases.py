"""The generators of issue 71's cases a and b (`cli/loop_cases.py`): each recording differs from its clean twin by
the undeclared effects only, well above the sensor's noise, and the spec is the nominal model."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "cli" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


lc = _load("latent_cases")
loop = _load("loop_cases")


@pytest.mark.slow  # six numpy simulations of 1000–4000 samples at 20 RK4 steps each: ~10 s
def test_each_recording_differs_from_its_twin_by_its_effects_only(tmp_path):
    for name, (_plant, clean, expected) in loop.CASES.items():
        info = loop.write_case(tmp_path, name, seed=2)
        rec = np.loadtxt(tmp_path / name / f"{name}.csv", delimiter=",", skiprows=1)
        twin = np.loadtxt(tmp_path / name / f"{name}_clean.csv", delimiter=",", skiprows=1)
        assert np.array_equal(rec[:, :2], twin[:, :2])  # the same times and input
        assert info["effect_rms"] > 5 * info["noise_rms"]  # the effects show, well above the noise (noisy case: 9.7×)
        # the twin is the nominal plant itself (latent_cases' own simulation, the same seed)
        assert np.allclose(twin[:, 2], lc.simulate(clean, seed=2)["y"], atol=1e-9)
        spec = (tmp_path / name / "model.yaml").read_text()
        assert "u" in spec and not any(str(e["coef"]) in spec for e in expected["effects"])  # nothing declared


def test_the_oscillators_offset_is_the_sensors():
    plant, clean, _ = loop.CASES["a_osc_two"]
    x = np.array([0.2, -1.0])
    assert plant.sensor(x) - clean.sensor(x) == loop.Y0
    f, g = plant.field(plant.params), clean.field(clean.params)
    assert (g(x, 0.0) - f(x, 0.0))[1] == pytest.approx(loop.K3 * 0.2**3)  # the cubic on the velocity row
