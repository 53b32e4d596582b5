"""cli/measured_cases.sh with a stub `mpsim` (what it runs for each case and twin: the data keys each file needs),
and cli/measured_scorecard.py's pass rule on hand-made diagnosis.json files."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

from tests.helpers import run_recipe

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("measured_scorecard", ROOT / "cli" / "measured_scorecard.py")
sc = importlib.util.module_from_spec(_spec)
sys.modules["measured_scorecard"] = sc
_spec.loader.exec_module(sc)


def _arg(call, key):
    return next(a.split("=", 1)[1] for a in call if a.startswith(key + "="))


def test_the_recipe_fits_and_diagnoses_each_recording_and_twin_with_its_data_keys(tmp_path):
    simulated = "b_axis_coulomb c_duffing d_input_gain d_deadzone"  # a_dfki is its own recipe's
    proc, calls = run_recipe(
        "measured_cases.sh", tmp_path, CASES=simulated, RECORD_S="0.3", TRAIN_ARGS="trainer.max_epochs=2"
    )
    assert proc.returncode == 0, proc.stderr
    out = tmp_path / "measured_cases.sh"
    trains = [c for c in calls if c[0] == "train"]
    diagnoses = [c for c in calls if c[0] == "diagnose"]
    assert len(trains) == len(diagnoses) == 8  # 4 cases × (recording, clean twin)
    for call in trains + diagnoses:
        assert {"data.control_columns=[u]", "data.observed=[q]", "data.segment=1.0", "data.input_hold=zoh"} <= set(call)
    by_path = {_arg(c, "data.path"): c for c in trains}
    b = by_path[str(out / "data/b_axis_coulomb/b_axis_coulomb.csv")]
    assert "data.columns={q:" in b and "enc_pos}" in b  # the encoder's column, one override (split by the stub)
    assert "trainer.max_epochs=2" in b and _arg(b, "model.spec") == str(out / "data/b_axis_coulomb/model.yaml")
    gain = by_path[str(out / "data/d_input_gain/d_input_gain_clean.csv")]
    assert {"data.time_column=null", "data.dt=0.002"} <= set(gain)
    d = next(c for c in diagnoses if _arg(c, "data.path").endswith("c_duffing.csv"))
    assert "fix=true" in d and _arg(d, "init") == str(out / "c_duffing/recording/train/checkpoints/best.ckpt")
    assert "0 of 4 simulated cases hold." in proc.stdout  # the stub trains nothing


def test_the_recipe_refuses_an_unknown_case(tmp_path):
    proc, calls = run_recipe("measured_cases.sh", tmp_path, CASES="b_axis_coulomb c_dufing")
    assert proc.returncode == 2 and "unknown value 'c_dufing' in CASES" in proc.stderr and calls == []


def _diagnosis(run: Path, verdict: str, named: list[tuple[str, str, float]], before=0.1, after=None) -> None:
    (run / "diagnose").mkdir(parents=True)
    effects = [{"kind": k, "label": f"d{row}/dt: {k}(v)", "values": {"coef": c}} for k, row, c in named]
    r = {"verdict": verdict, "effects_named": effects, "before": {"rollout_rmse": before}}
    r["judgement"] = {"trials": [{"label": e["label"]} for e in effects]}
    r["after"] = None if after is None else {"rollout_rmse": after}
    (run / "diagnose" / "diagnosis.json").write_text(json.dumps(r))
    (run / "wall_s").write_text("12\n")


def _truth(out: Path, case: str, kind, coef: float) -> None:
    (out / "data" / case).mkdir(parents=True)
    miss = {"kind": kind, "target": "v", "source": "v", "coef": coef, "physical": {"gain": 0.8}}
    (out / "data" / case / "truth.json").write_text(json.dumps({"missing_effect": miss}))


def test_the_pass_rule(tmp_path):
    _truth(tmp_path, "fric", "DryFriction", 0.2)
    _diagnosis(tmp_path / "fric/recording", "effects named", [("DryFriction", "v", 0.21)], 0.1, 0.01)
    _diagnosis(tmp_path / "fric/clean", "nothing missing", [])
    row, ok = sc.score(tmp_path, "fric")
    assert ok and "0.21 vs 0.2 (5.0%)" in row and row[-2] == "12 + 12" and row[5] == "DryFriction(v)"
    _truth(tmp_path, "far", "DryFriction", 0.2)  # 15 % off
    _diagnosis(tmp_path / "far/recording", "effects named", [("DryFriction", "v", 0.23)], 0.1, 0.01)
    _diagnosis(tmp_path / "far/clean", "nothing missing", [])
    assert not sc.score(tmp_path, "far")[1]
    _truth(tmp_path, "gain", None, -0.4)  # outside the library: unexplained, nothing named
    _diagnosis(tmp_path / "gain/recording", "effects named", [("DryFriction", "v", 0.2)], 0.1, 0.05)
    _diagnosis(tmp_path / "gain/clean", "unexplained structured residual", [])
    assert not sc.score(tmp_path, "gain")[1]
    _truth(tmp_path, "gain2", None, -0.4)
    _diagnosis(tmp_path / "gain2/recording", "unexplained structured residual", [])
    _diagnosis(tmp_path / "gain2/clean", "unexplained structured residual", [])
    assert sc.score(tmp_path, "gain2")[1]
    _truth(tmp_path, "worse", "DryFriction", 0.2)  # a fix worse than the model given
    _diagnosis(tmp_path / "worse/recording", "effects named", [("DryFriction", "v", 0.2)], 0.1, 0.2)
    _diagnosis(tmp_path / "worse/clean", "nothing missing", [])
    assert not sc.score(tmp_path, "worse")[1]
    _truth(tmp_path, "fp", "DryFriction", 0.2)  # named on the clean twin
    _diagnosis(tmp_path / "fp/recording", "effects named", [("DryFriction", "v", 0.2)], 0.1, 0.01)
    _diagnosis(tmp_path / "fp/clean", "effects named", [("Bias", "v", 0.01)], 0.1, 0.09)
    assert not sc.score(tmp_path, "fp")[1]
    _truth(tmp_path, "missing", "DryFriction", 0.2)  # never ran
    row, ok = sc.score(tmp_path, "missing")
    assert not ok and row[2] == "not run"
    assert sc.main([str(tmp_path)]) == 0 and "2 of 7 simulated cases hold." in (tmp_path / "scorecard.md").read_text()


def test_the_real_row_reports_what_was_measured(tmp_path):
    assert sc.real_row(tmp_path / "a_dfki") is None  # the recipe did not run there: no row
    _diagnosis(tmp_path / "a_dfki", "unexplained structured residual", [], 0.05)
    diag = tmp_path / "a_dfki" / "diagnose" / "diagnosis.json"
    r = json.loads(diag.read_text())
    r["judgement"].update(error_given=1.46e-4, error_null=1.6e-8)
    diag.write_text(json.dumps(r))
    row, ok = sc.real_row(tmp_path / "a_dfki")
    assert ok and row[2] == "unexplained structured residual" and row[4] == "(no truth)" and row[-1] == "reported"
    assert "null level 1.6e-08" in row[6]
    _truth(tmp_path, "fric", "DryFriction", 0.2)
    _diagnosis(tmp_path / "fric/recording", "effects named", [("DryFriction", "v", 0.21)], 0.1, 0.01)
    _diagnosis(tmp_path / "fric/clean", "nothing missing", [])
    assert sc.main([str(tmp_path)]) == 0
    text = (tmp_path / "scorecard.md").read_text()
    assert "| a_dfki |" in text and "1 of 1 simulated cases hold." in text and "no truth to hold to" in text
