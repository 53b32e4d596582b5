"""`mpsim diagnose` end to end, in this process: train a white-box model on data with a hidden effect, find it,
fix it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.helpers import TINY_TRAIN, run_mpsim, run_mpsim_ok

SMALL = ["data.n_train=32", "data.n_val=8", "data.n_test=16", "trainer.progress=false", "diagnose.n_boot=30"]


def test_hidden_damping_found_added_and_error_drops(tmp_path):
    run_mpsim_ok(["train", "experiment=pendulum_damped", "trainer.max_epochs=15", *SMALL[:-1]], tmp_path)
    proc = run_mpsim_ok(
        [
            "diagnose",
            "experiment=pendulum_damped",
            "init=pendulum2_damped.ckpt",
            "fix=true",
            "trainer.max_epochs=10",
            *SMALL,
        ],
        tmp_path,
    )
    assert "effects named" in proc.stdout
    (run,) = [p.parent for p in (tmp_path / "outputs" / "diagnose").rglob("diagnosis.json")]
    result = json.loads((run / "diagnosis.json").read_text())
    assert result["verdict"] == "effects named" and result["exit_code"] == 0
    (found,) = result["effects_named"]
    assert found["label"] == "domega/dt: LinearDamping(omega)"
    assert found["vs_truth"]["relative_error"]["coef"] < 0.05
    lo, hi = found["interval"]["coef"]
    assert lo <= found["values"]["coef"] <= hi  # the interval is the reported coefficient's
    assert result["screen"]["searched_rows"] == ["omega"]  # θ̇ = ω is kinematic: not searched
    (fixed,) = result["fixed_effects"]
    assert fixed["vs_truth"]["relative_error"]["coef"] < 0.05
    assert result["after"]["rollout_rmse"] * 10 <= result["before"]["rollout_rmse"]
    # one round: the damping is added, and the fixed model, diagnosed again, lacks nothing
    (only,) = result["rounds"]
    assert only["added"] == [found["label"]] and only["then"]["named"] == []
    for name in ("diagnosis.md", "plots/residual.png", "plots/explained_variance.png", "plots/before_after.png"):
        assert (run / name).is_file(), name
    assert result["fixed_checkpoint"] and Path(result["fixed_checkpoint"]).is_file()


def test_clean_data_gives_nothing_missing(tmp_path):
    clean = ["experiment=pendulum_damped", "system.effects=[]", "system.name=pendulum2_clean"]
    run_mpsim_ok(["train", *clean, "trainer.max_epochs=15", *SMALL[:-1]], tmp_path)
    proc = run_mpsim(["diagnose", *clean, "init=pendulum2_clean.ckpt", "fix=true", *SMALL], tmp_path)
    assert proc.code == 10, proc.err[-2000:]  # the verdict's own exit code
    assert "nothing missing" in proc.stdout
    (run,) = [p.parent for p in (tmp_path / "outputs" / "diagnose").rglob("diagnosis.json")]
    result = json.loads((run / "diagnosis.json").read_text())
    assert result["verdict"] == "nothing missing" and result["effects_named"] == [] and result["after"] is None


def test_diagnose_needs_a_checkpoint(tmp_path):
    proc = run_mpsim(["diagnose"], tmp_path)
    assert proc.code == 2 and "Traceback" not in proc.err
    (line,) = proc.error_lines()
    assert line.startswith("mpsim diagnose: error:") and "init=" in line
    assert not [p for p in tmp_path.rglob("*") if p.is_file()]  # refused before a run directory exists


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory):
    """A tiny trained pendulum2 checkpoint, so that a bad setting is what the command refuses (not the init)."""
    ws = tmp_path_factory.mktemp("diagnose_ckpt")
    run_mpsim_ok(["train", *TINY_TRAIN, "eval.plots=false"], ws)
    return ws / "checkpoints" / "pendulum2.ckpt"


@pytest.mark.parametrize(
    "bad, match",
    [
        ("diagnose.n_boot=many", "diagnose.n_boot=many"),
        ("diagnose.kinds=[Wobble]", "unknown effect kind 'Wobble'"),
    ],
)
def test_bad_diagnose_settings(tmp_path, tiny_ckpt, bad, match):
    proc = run_mpsim(["diagnose", f"init={tiny_ckpt}", bad, *TINY_TRAIN[2:]], tmp_path)
    assert proc.code == 2 and "Traceback" not in proc.err, (proc.code, proc.err[-2000:])
    (line,) = proc.error_lines()
    assert match in line
    assert not [p for p in tmp_path.rglob("*") if p.is_file()]
