"""The generators of issue 70's cases c (`cli/latent_cases.py`): what each case is said to be, checked on its data."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("latent_cases", ROOT / "cli" / "latent_cases.py")
assert _spec is not None and _spec.loader is not None
lc = importlib.util.module_from_spec(_spec)
sys.modules["latent_cases"] = lc  # dataclasses look their module up
_spec.loader.exec_module(lc)


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_each_case_records_only_its_sensor_and_is_deterministic(tmp_path):
    for name, case in lc.CASES.items():
        info = lc.write_case(tmp_path, name, seed=3)
        header = (tmp_path / name / f"{name}.csv").read_text().splitlines()[0]
        assert header == f"t,u,{case.column}" and info["samples"] == case.n
        assert json.loads((tmp_path / name / "truth.json").read_text()) == info
        again = lc.simulate(case, seed=3)
        assert np.array_equal(again["x"], np.load(tmp_path / name / "truth.npz")["x"])


def test_the_oscillator_is_sampled_at_8_6_samples_a_period_of_its_resonance():
    case = lc.CASES["oscillator"]
    omega = math.sqrt(case.params["k"] / case.params["m"])
    assert abs(2 * math.pi / omega / case.dt - 8.6) < 1e-9


def test_the_tanks_stay_filled_and_the_belt_speed_changes_sign():
    tanks = lc.simulate(lc.CASES["tanks"])["x"]
    assert tanks.min() > 1.0  # levels > 0: Torricelli's outflow is defined throughout
    belt = lc.simulate(lc.CASES["abs_speed"])
    s = belt["x"][:, 1]
    assert (s > 0.05).mean() > 0.2 and (s < -0.05).mean() > 0.2  # the sensor's |s| hides a real sign
    assert np.all(belt["y"] >= -0.05)  # it reads |s| (plus noise)
