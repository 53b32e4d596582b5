"""`mpsim` end to end, in subprocesses, on tiny configs."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from tests.conftest import TINY_TRAIN, run_cli


def _runs(root: Path, task: str = "train") -> list[Path]:
    return sorted(p.parent for p in (root / "outputs" / task).rglob("summary.json"))


@pytest.fixture(scope="module")
def lorenz_ws(tmp_path_factory):
    """A workspace where `mpsim train system=lorenz3` has run (tiny)."""
    ws = tmp_path_factory.mktemp("lorenz")
    run_cli(["train", "system=lorenz3", *TINY_TRAIN], ws, check=True)
    return ws


def test_default_train_writes_every_output(tmp_path):
    proc = run_cli(["train", *TINY_TRAIN], tmp_path, check=True)
    assert "mpsim train: pendulum2 (scratch)" in proc.stdout and "epochs_x_min_error" in proc.stdout
    (run,) = _runs(tmp_path)
    metrics = pd.read_csv(run / "metrics.csv")
    assert list(metrics.columns[:5]) == ["epoch", "train_loss", "val_error", "test_error", "lr"]
    assert "wall_time" in metrics.columns and len(metrics) == 4  # epoch 0 (untrained) + 3
    summary = json.loads((run / "summary.json").read_text())
    for key in ("min_test_error", "min_test_error_epoch", "epochs_x_min_error", "final", "wall_time"):
        assert key in summary, key
    assert summary["model"]["n_params"] == 1413
    assert summary["epochs_x_min_error"] == pytest.approx(summary["min_test_error"] * summary["min_test_error_epoch"])
    for name in (
        "checkpoints/best.ckpt",
        "checkpoints/last.ckpt",
        "plots/learning_curves.png",
        "plots/trajectories.png",
        "plots/error_growth.png",
        ".hydra/overrides.yaml",
        "train.log",
    ):
        assert (run / name).is_file(), name
    assert (tmp_path / "checkpoints" / "pendulum2.ckpt").is_file()


def test_same_seed_same_summary(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for ws in (a, b):
        ws.mkdir()
        run_cli(["train", *TINY_TRAIN], ws, check=True)
    sa, sb = (json.loads((_runs(ws)[0] / "summary.json").read_text()) for ws in (a, b))
    drop = ("wall_time", "command_time", "run_dir", "checkpoint", "exported")
    assert {k: v for k, v in sa.items() if k not in drop} == {k: v for k, v in sb.items() if k not in drop}


def test_lorenz3_then_finetune_zeroshot_eval_simulate(lorenz_ws):
    ws = lorenz_ws
    assert (ws / "checkpoints" / "lorenz3.ckpt").is_file()
    run_cli(["train", "system=lorenz10", "init=lorenz3.ckpt", *TINY_TRAIN], ws, check=True)
    fine = json.loads((_runs(ws)[-1] / "summary.json").read_text())
    assert fine["mode"] == "finetune" and fine["init"].endswith("lorenz3.ckpt") and fine["system"]["n_nodes"] == 10
    assert (ws / "checkpoints" / "lorenz10.ckpt").is_file()

    proc = run_cli(["train", "mode=zeroshot", "init=lorenz3.ckpt", "system=lorenz10", *TINY_TRAIN], ws, check=True)
    assert "zero-shot" in proc.stdout
    zs = json.loads((_runs(ws)[-1] / "summary.json").read_text())
    assert zs["mode"] == "zeroshot" and zs["test_error"] > 0 and not (_runs(ws)[-1] / "metrics.csv").exists()

    run_cli(["eval", "init=lorenz3.ckpt", "system=lorenz10", "data.n_test=3", "data.horizon=10"], ws, check=True)
    ev = json.loads((_runs(ws, "eval")[-1] / "summary.json").read_text())
    assert ev["trained_on"] == "lorenz3" and ev["system"]["name"] == "lorenz10"

    run_cli(["simulate", "system=lorenz10", "init=lorenz3.ckpt", "format=csv", "n=2", "data.horizon=5"], ws, check=True)
    (sim,) = _runs(ws, "simulate")
    for name in ("trajectories.csv", "trajectories_edges.csv", "trajectories.json", "trajectories_model.csv"):
        assert (sim / name).is_file(), name
    frame = pd.read_csv(sim / "trajectories.csv")
    assert list(frame.columns) == ["traj", "t", "node", "x", "y", "z"] and len(frame) == 2 * 6 * 10


def test_trained_file_data_round_trip(lorenz_ws, tmp_path):
    # simulate → CSV → train on the file as measured data
    run_cli(["simulate", "system=pendulum2", "format=csv", "n=9", "data.horizon=10"], tmp_path, check=True)
    (sim,) = _runs(tmp_path, "simulate")
    run_cli(["train", f"data.path={sim / 'trajectories.csv'}", *TINY_TRAIN], tmp_path, check=True)
    summary = json.loads((_runs(tmp_path)[-1] / "summary.json").read_text())
    assert (
        summary["data"]["source"].endswith("trajectories.csv") and summary["data"]["train"] == 7
    )  # 9 trajectories split 0.7/0.15/0.15 → 7/1/1


def test_sweep_gives_every_job_its_own_directory(lorenz_ws):
    ws = lorenz_ws
    proc = run_cli(
        ["train", "-m", *TINY_TRAIN, "system=lorenz10", "data.n_train=4,6", "init=lorenz3.ckpt,null"], ws, check=True
    )
    jobs = sorted(p.parent for p in (ws / "outputs" / "multirun").rglob("summary.json"))
    assert len(jobs) == 4 and len({j.name for j in jobs}) == 4, proc.stderr
    modes = sorted(json.loads((j / "summary.json").read_text())["mode"] for j in jobs)
    assert modes == ["finetune", "finetune", "scratch", "scratch"]
    report = run_cli(["report", "runs=[outputs/multirun]"], ws, check=True)
    assert "data.n_train" in report.stdout and "init" in report.stdout


def test_joblib_launcher_runs_jobs_in_parallel_processes(tmp_path):
    proc = run_cli(
        ["train", "-m", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "seed=0,1", *TINY_TRAIN],
        tmp_path,
        check=True,
    )
    jobs = sorted(p.parent for p in (tmp_path / "outputs" / "multirun").rglob("summary.json"))
    assert len(jobs) == 2, proc.stderr
    assert "Joblib.Parallel" in proc.stderr or "joblib" in proc.stderr.lower()


def test_resume_after_interrupt_matches_an_uninterrupted_run(tmp_path):
    args = [
        "train",
        "trainer=quick",
        "trainer.max_epochs=8",
        "trainer.progress=false",
        "data.n_train=8",
        "data.n_val=4",
        "data.n_test=4",
        "data.horizon=10",
    ]
    full_ws, cut_ws = tmp_path / "full", tmp_path / "cut"
    full_ws.mkdir(), cut_ws.mkdir()
    run_cli(args, full_ws, check=True)
    proc = subprocess.Popen(
        [sys.executable, "-m", "mpsim.cli", *args],
        cwd=cut_ws,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.time() + 120
    while time.time() < deadline:
        metrics = list((cut_ws / "outputs").rglob("metrics.csv"))
        if metrics and len(metrics[0].read_text().splitlines()) >= 4:  # header + epochs 0..2
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    if proc.returncode == 0:
        pytest.skip("the run finished before it could be interrupted")
    assert proc.returncode == 130 and "resume=true" in err
    run_cli([*args, "resume=true"], cut_ws, check=True)
    (full_run,), (cut_run,) = _runs(full_ws), _runs(cut_ws)
    cols = ["epoch", "train_loss", "val_error", "test_error", "lr"]
    a, b = pd.read_csv(full_run / "metrics.csv")[cols], pd.read_csv(cut_run / "metrics.csv")[cols]
    pd.testing.assert_frame_equal(a, b)
    sa, sb = (json.loads((r / "summary.json").read_text()) for r in (full_run, cut_run))
    assert sa["min_test_error"] == sb["min_test_error"] and sa["test"]["rmse"] == sb["test"]["rmse"]


def _fails(args, cwd, match, code=2):
    before = {p for p in cwd.rglob("*") if p.is_file()}
    proc = run_cli(args, cwd)
    assert proc.returncode == code, (proc.returncode, proc.stdout, proc.stderr)
    assert match in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr
    new = {p for p in cwd.rglob("*") if p.is_file()} - before
    # nothing half-written: no results, no checkpoints, no partial data (only Hydra's run record and log)
    assert not [p for p in new if p.suffix in (".ckpt", ".csv", ".png", ".npz") or p.name == "summary.json"], new
    return proc


def test_bad_inputs_end_with_one_clear_message(lorenz_ws, tmp_path):
    ws = lorenz_ws
    assert "Could not find 'system/lorenz4'" in run_cli(["train", "system=lorenz4"], ws).stderr
    _fails(["train", "init=nowhere.ckpt", *TINY_TRAIN], ws, "init=nowhere.ckpt: no such checkpoint")
    _fails(["train", "mode=finetune", *TINY_TRAIN], ws, "mode=finetune needs init=<checkpoint>")
    _fails(["train", "mode=zeroshot", *TINY_TRAIN], ws, "mode=zeroshot needs init=<checkpoint>")
    _fails(
        ["train", "system=pendulum2", "init=lorenz3.ckpt", *TINY_TRAIN],
        ws,
        "was trained on lorenz3 (3 states ['x', 'y', 'z']",
    )
    _fails(
        ["train", "system=lorenz10", "init=lorenz3.ckpt", "model.message_size=5", *TINY_TRAIN],
        ws,
        "model.message_size: checkpoint 3, config 5",
    )
    _fails(["train", "system=lorenz3", "system.coupling=strong", *TINY_TRAIN], ws, "expects float")
    (tmp_path / "bad.csv").write_text("traj,t,node,theta\n0,0.0,0,1.0\n0,0.1,0,nan\n")
    (tmp_path / "bad_edges.csv").write_text("src,dst\n")
    _fails(["train", f"data.path={tmp_path / 'bad.csv'}", *TINY_TRAIN], ws, "row 3, column 'theta' is empty")
    assert run_cli(["frobnicate"], ws).returncode == 2
    typo = run_cli(["train", "trainer.lrr=1"], ws)
    assert typo.returncode != 0 and "trainer.lrr" in typo.stderr


def test_bench_writes_table_and_plot(tmp_path):
    run_cli(
        ["bench", "bench.nodes=[2,4]", "bench.batches=[1,2]", "bench.steps=3", "bench.repeats=1"], tmp_path, check=True
    )
    (run,) = sorted(p.parent for p in (tmp_path / "outputs" / "bench").rglob("bench.md"))
    assert "fwd_bwd_s" in (run / "bench.md").read_text() and (run / "plots" / "mpnode_scaling.png").is_file()
