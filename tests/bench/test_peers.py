"""`mpsim bench bench=peers`: PySINDy beside the residual loop (the optional extra `mpsim[peers]`)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from mpsim import effects as fx
from mpsim.bench.peers import CASES, PeersBench, judge, mpsim_side, pysindy_side, require_pysindy
from mpsim.errors import ConfigError
from mpsim.models.equations import EquationsModel
from mpsim.systems.equations import EquationsSystem
from mpsim.systems.simulation import simulate

SPECS = Path(__file__).resolve().parents[2] / "examples" / "diagnose_cases"
OSCILLATOR = {"states": ["x", "v"], "equations": {"x": "v", "v": "-k*x"}, "params": {"k": 4.0}, "nodes": 1}


def test_a_damped_oscillators_residual_is_named_linear_damping_within_10_percent():
    pytest.importorskip("pysindy")
    truth = {**OSCILLATOR, "init": {"x": [-1.0, 1.0], "v": [-1.0, 1.0]}, "dt": 0.05, "horizon": 200}
    system = EquationsSystem(spec=truth, effects=[fx.LinearDamping(coef=0.3, target="v")])
    data = simulate(system, 8, seed=0)
    named, seconds = pysindy_side(data, EquationsModel(2, spec=OSCILLATOR))
    assert [(e["kind"], e["row"]) for e in named] == [("LinearDamping", "v")], named
    assert named[0]["values"]["coef"] == pytest.approx(0.3, rel=0.10)
    assert seconds > 0


def test_without_pysindy_the_suite_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "pysindy", None)  # `import pysindy` now raises ImportError
    with pytest.raises(ConfigError, match=r"pip install 'mpsim\[peers\]'"):
        require_pysindy()
    with pytest.raises(ConfigError, match=r"mpsim\[peers\]"):
        PeersBench(cases=["a_undamped"], twins=False, specs=str(SPECS)).run()


def test_the_mpsim_column_is_read_and_judged_as_the_scorecard_does(tmp_path):
    run = tmp_path / "a_damped"
    (run / "diagnose").mkdir(parents=True)
    (run / "wall_s").write_text("134\n")
    effect = {"kind": "LinearDamping", "label": "dv/dt: LinearDamping(v)", "values": {"coef": 0.2955}}
    diagnosis = {
        "verdict": "effects named",
        "effects_named": [effect],
        "before": {"rollout_rmse": 0.9},
        "after": {"rollout_rmse": 0.01},
    }
    (run / "diagnose" / "diagnosis.json").write_text(json.dumps(diagnosis))
    mine = mpsim_side(run)
    assert mine is not None and mine["seconds"] == 134
    assert judge(CASES["a_damped"], mine["named"], mine["verdict"], mine["worse"]) == (True, "1.50%")
    assert judge(CASES["a_damped"], mine["named"] * 2)[0] is False  # a second name is a false claim
    assert judge(CASES["a_undamped"], mine["named"])[0] is False
    assert judge(CASES["e_pendulum_sin2"], [], "unexplained structured residual") == (True, "")
    assert mpsim_side(tmp_path / "b_vdp") is None


def test_a_case_without_a_run_says_not_run(tmp_path):
    pytest.importorskip("pysindy")
    rows = PeersBench(cases=["a_undamped"], twins=False, runs=str(tmp_path), specs=str(SPECS)).run()
    assert len(rows) == 1 and rows[0]["mpsim named (fitted)"] == "not run" and rows[0]["params"] == "spec"
    assert rows[0]["PySINDy right"] in ("yes", "NO")


def test_bad_settings_are_refused():
    with pytest.raises(ConfigError, match="unknown case"):
        PeersBench(cases=["nope"], specs=str(SPECS))
    with pytest.raises(ConfigError, match="bench.specs"):
        PeersBench(specs="/nonexistent")
    with pytest.raises(ConfigError, match="bench.params"):
        PeersBench(specs=str(SPECS), params="guess")
    with pytest.raises(ConfigError, match="bench.extend"):
        PeersBench(specs=str(SPECS), extend=["wavelets"])
