"""`mpsim diagnose` end to end, in this process: train a white-box model on data with a hidden effect, find it,
fix it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mpsim.diagnose.stats import critical
from tests.helpers import TINY_TRAIN, run_mpsim, run_mpsim_ok

SMALL = ["data.n_train=32", "data.n_val=8", "data.n_test=16", "trainer.progress=false", "diagnose.n_boot=30"]


@pytest.mark.slow  # a whole residual-loop run: `pytest -m slow` (.ci/run runs it)
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
    # the acceptance test's own numbers: Student's t bar for 16 held-out recordings, cleared, and shown
    assert found["n_heldout"] == 16 and found["bar_se"] == pytest.approx(critical(2.0, 16))
    assert found["log_ratio"] - max(found["null_log_ratio"], 0.0) > found["bar_se"] * found["log_ratio_se"]
    assert "standard errors above" in found["test"] and found["test"] in (run / "diagnosis.md").read_text()
    assert "over 16 held-out recordings" in proc.stdout  # on the console too, under the effect
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


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
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
        # one or two held-out trajectories cannot judge a candidate (no standard error, or a bar of 14 of them)
        ("data.n_test=2", "needs at least 3; data.n_test=2. Give data.n_test=3 or more"),
    ],
)
def test_bad_diagnose_settings(tmp_path, tiny_ckpt, bad, match):
    proc = run_mpsim(["diagnose", f"init={tiny_ckpt}", *TINY_TRAIN[2:], bad], tmp_path)
    assert proc.code == 2 and "Traceback" not in proc.err, (proc.code, proc.err[-2000:])
    (line,) = proc.error_lines()
    assert match in line
    assert not [p for p in tmp_path.rglob("*") if p.is_file()]


def test_a_file_with_too_few_held_out_trajectories_is_refused_with_a_split_that_holds_out_enough(tmp_path, tiny_ckpt):
    """8 recordings at the default shares hold out 1: refused before any work, with a data.split that holds out 3."""
    run_mpsim_ok(["simulate", "n=8", "data.horizon=10", "hydra.run.dir=sim"], tmp_path)
    data = tmp_path / "sim" / "trajectories.npz"
    proc = run_mpsim(["diagnose", f"init={tiny_ckpt}", f"data.path={data}", "hydra.run.dir=out"], tmp_path)
    assert proc.code == 2 and "Traceback" not in proc.err, (proc.code, proc.err[-2000:])
    (line,) = proc.error_lines()
    assert "of the file's 8 trajectories holds out 1" in line
    shares = [float(v) for v in line.split("data.split=[")[-1].split("]")[0].split(",")]
    assert len(shares) == 3 and sum(shares) == pytest.approx(1.0) and round(8 * shares[2]) >= 3
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
@pytest.mark.scaling  # ~20 s of spawned processes: run by .ci/run's `-m scaling` step, outside the default suite
def test_a_networks_finetunes_run_in_parallel_processes_with_the_serial_results(tmp_path):
    """fix=true on an MP-NODE finetunes a control and each candidate; diagnose.jobs=2 runs them in two spawned
    processes, and must give what one process gives (same seed, epochs and data; one thread each)."""
    # a drive: a network without a clock cannot absorb it, so the screen has a candidate even after a short training
    drive = "+system.effects=[{_target_: mpsim.effects.PeriodicForcing, amplitude: 2.0, omega: 5.0, target: omega}]"
    small = ["data.n_train=16", "data.n_val=4", "data.n_test=8", "trainer.progress=false"]
    net = ["system=pendulum2", drive, "system.name=pd", "model=mpnode", "model.hidden=16", *small]
    run_mpsim_ok(["train", *net, "trainer.max_epochs=3"], tmp_path)
    results = {}
    for jobs in (1, 2):
        args = ["diagnose", *net, "diagnose.n_boot=10", "diagnose.rounds=1", "init=pd.ckpt", "fix=true"]
        run_mpsim(
            [*args, "trainer.max_epochs=1", f"diagnose.jobs={jobs}", f"hydra.run.dir=outputs/jobs{jobs}"], tmp_path
        )
        run = tmp_path / "outputs" / f"jobs{jobs}"
        results[jobs] = json.loads((run / "diagnosis.json").read_text())
        (first,) = results[jobs]["finetuned"][:1]
        assert first["trials"], "the screen found no candidate: the parallel path was not exercised"
        assert (run / "fix" / "round1" / "control" / "checkpoints" / "best.ckpt").is_file()
        finetuned = sorted((run / "fix" / "round1").glob("*/checkpoints/best.ckpt"))
        assert len(finetuned) == 1 + len(first["trials"])  # the control and every candidate wrote a checkpoint
    serial, parallel = (r["finetuned"][0] for r in (results[1], results[2]))
    assert parallel["error_control"] == pytest.approx(serial["error_control"], rel=1e-5)
    assert [t["label"] for t in parallel["trials"]] == [t["label"] for t in serial["trials"]]
    for a, b in zip(parallel["trials"], serial["trials"], strict=True):
        assert a["error_after"] == pytest.approx(b["error_after"], rel=1e-5)
    assert results[2]["verdict"] == results[1]["verdict"]
