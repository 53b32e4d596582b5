"""`mpsim diagnose` end to end: train a white-box model on data with a hidden effect, find it, fix it."""

from __future__ import annotations

import json

import pytest

from tests.conftest import run_cli

SMALL = ["data.n_train=32", "data.n_val=8", "data.n_test=16", "trainer.progress=false", "diagnose.n_boot=30"]


def test_hidden_damping_found_added_and_error_drops(tmp_path):
    run_cli(["train", "experiment=pendulum_damped", "trainer.max_epochs=15", *SMALL[:-1]], tmp_path, check=True)
    proc = run_cli(["diagnose", "experiment=pendulum_damped", "init=pendulum2_damped.ckpt", "fix=true",
                    "trainer.max_epochs=10", *SMALL], tmp_path, check=True)
    assert "effects found" in proc.stdout
    (run,) = [p.parent for p in (tmp_path / "outputs" / "diagnose").rglob("diagnosis.json")]
    result = json.loads((run / "diagnosis.json").read_text())
    (found,) = result["effects_found"]
    assert found["label"] == "domega/dt: LinearDamping(omega)"
    assert found["vs_truth"]["relative_error"]["coef"] < 0.1
    (fixed,) = result["fixed_effects"]
    assert fixed["vs_truth"]["relative_error"]["coef"] < 0.1
    assert result["after"]["rollout_rmse"] * 10 <= result["before"]["rollout_rmse"]
    # one round: the damping is added, and the finetuned model, diagnosed again, lacks nothing (its own damping
    # coefficient is refit as the model's parameter, not found a second time)
    (only,) = result["rounds"]
    assert only["added"] == found["label"] and only["then_found"] == []
    assert result["effects_named"] == [found["label"]] and result["not_confirmed"] == []
    for name in ("diagnosis.md", "plots/residual.png", "plots/explained_variance.png", "plots/before_after.png",
                 "fix/round1/checkpoints/best.ckpt"):
        assert (run / name).is_file(), name


def test_clean_data_gives_no_effect_found(tmp_path):
    clean = ["experiment=pendulum_damped", "system.effects=[]", "system.name=pendulum2_clean"]
    run_cli(["train", *clean, "trainer.max_epochs=15", *SMALL[:-1]], tmp_path, check=True)
    proc = run_cli(["diagnose", *clean, "init=pendulum2_clean.ckpt", "fix=true", *SMALL], tmp_path, check=True)
    assert "no effect found" in proc.stdout and "why" in proc.stdout
    (run,) = [p.parent for p in (tmp_path / "outputs" / "diagnose").rglob("diagnosis.json")]
    result = json.loads((run / "diagnosis.json").read_text())
    assert result["verdict"] == "no effect found" and result["effects_found"] == [] and result["after"] is None


def test_diagnose_needs_a_checkpoint(tmp_path):
    proc = run_cli(["diagnose"], tmp_path)
    assert proc.returncode != 0 and "init" in proc.stderr


@pytest.mark.parametrize("bad", ["diagnose.n_boot=many", "diagnose.kinds=[Wobble]"])
def test_bad_diagnose_settings(tmp_path, bad):
    proc = run_cli(["diagnose", "init=x.ckpt", bad], tmp_path)
    assert proc.returncode != 0
