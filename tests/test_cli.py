"""`mpsim` end to end on tiny configs: in this process (`tests.helpers.run_mpsim`), except the entry points'
own exit codes and Ctrl-C, and the joblib launcher's worker processes, which need real processes."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
import yaml

from tests.helpers import TINY_TRAIN, run_cli, run_mpsim, run_mpsim_ok


def _runs(root: Path, task: str = "train") -> list[Path]:
    return sorted(p.parent for p in (root / "outputs" / task).rglob("summary.json"))


@pytest.fixture(scope="module")
def lorenz_ws(tmp_path_factory):
    """A workspace where `mpsim train system=lorenz3` has run (tiny)."""
    ws = tmp_path_factory.mktemp("lorenz")
    run_mpsim_ok(["train", "system=lorenz3", *TINY_TRAIN, "eval.plots=false"], ws)
    return ws


def test_default_train_writes_every_output(tmp_path):
    proc = run_mpsim_ok(["train", *TINY_TRAIN], tmp_path)
    assert "mpsim train: pendulum2 (scratch)" in proc.stdout and "epochs_x_min_error" in proc.stdout
    (run,) = _runs(tmp_path)
    metrics = pd.read_csv(run / "metrics.csv")
    assert list(metrics.columns[:5]) == ["epoch", "train_loss", "val_error", "test_error", "lr"]
    assert "wall_time" in metrics.columns and len(metrics) == 4  # epoch 0 (untrained) + 3
    summary = json.loads((run / "summary.json").read_text())
    for key in ("min_test_error", "min_test_error_epoch", "epochs_x_min_error", "final", "wall_time"):
        assert key in summary, key
    assert summary["model"]["n_params"] == 1413
    where = "cuda:0 (" if torch.cuda.is_available() else "cpu ("  # device=auto; the summary says which it chose
    assert summary["device"].startswith(where) and f"on {summary['device']}" in proc.stdout
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
    assert "scratch: MPNODE (1,413 params) on pendulum2" in (run / "train.log").read_text()
    assert (tmp_path / "checkpoints" / "pendulum2.ckpt").is_file()


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_same_seed_same_summary(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for ws in (a, b):
        ws.mkdir()
        run_mpsim_ok(["train", *TINY_TRAIN, "eval.plots=false"], ws)
    sa, sb = (json.loads((_runs(ws)[0] / "summary.json").read_text()) for ws in (a, b))
    drop = ("wall_time", "command_time", "run_dir", "checkpoint", "exported")
    assert {k: v for k, v in sa.items() if k not in drop} == {k: v for k, v in sb.items() if k not in drop}
    other = tmp_path / "c"
    other.mkdir()
    run_mpsim_ok(["train", *TINY_TRAIN, "eval.plots=false", "seed=1"], other)
    sc = json.loads((_runs(other)[0] / "summary.json").read_text())
    assert sc["final"] != sa["final"]  # the seed matters: equal summaries above are not a constant


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_lorenz3_then_finetune_zeroshot_eval_simulate(lorenz_ws):
    ws = lorenz_ws
    assert (ws / "checkpoints" / "lorenz3.ckpt").is_file()
    run_mpsim_ok(["train", "system=lorenz10", "init=lorenz3.ckpt", *TINY_TRAIN, "eval.plots=false"], ws)
    fine = json.loads((_runs(ws)[-1] / "summary.json").read_text())
    assert fine["mode"] == "finetune" and fine["init"].endswith("lorenz3.ckpt") and fine["system"]["n_nodes"] == 10
    assert (ws / "checkpoints" / "lorenz10.ckpt").is_file()

    args = ["train", "mode=zeroshot", "init=lorenz3.ckpt", "system=lorenz10", *TINY_TRAIN, "eval.plots=false"]
    proc = run_mpsim_ok(args, ws)
    assert "zero-shot" in proc.stdout
    zs = json.loads((_runs(ws)[-1] / "summary.json").read_text())
    assert zs["mode"] == "zeroshot" and zs["test_error"] > 0 and not (_runs(ws)[-1] / "metrics.csv").exists()

    args = [
        "eval",
        "init=lorenz3.ckpt",
        "system=lorenz10",
        "data.n_test=3",
        "data.horizon=10",
        "eval.save_predictions=true",
    ]
    run_mpsim_ok(args, ws)
    (ev_run,) = _runs(ws, "eval")
    ev = json.loads((ev_run / "summary.json").read_text())
    assert ev["trained_on"] == "lorenz3" and ev["system"]["name"] == "lorenz10"
    assert list((ev_run / "plots").glob("*.png"))
    # the saved test split and rollout are the ones the metrics were computed on
    with np.load(ev_run / "test.npz") as truth, np.load(ev_run / "test_model.npz") as model:
        x, pred = truth["x"], model["x"]
        assert x.shape == pred.shape == (3, 11, 10, 3) and np.array_equal(truth["t"], model["t"])
    assert np.allclose(pred[:, 0], x[:, 0], atol=1e-5) and not np.allclose(pred[:, 1:], x[:, 1:])
    assert np.sqrt(((pred - x)[:, 1:] ** 2).mean()) == pytest.approx(ev["test"]["rmse_raw"], rel=1e-4)

    run_mpsim_ok(["simulate", "system=lorenz10", "init=lorenz3.ckpt", "format=csv", "n=2", "data.horizon=5"], ws)
    (sim,) = _runs(ws, "simulate")
    for name in ("trajectories.csv", "trajectories_edges.csv", "trajectories.json", "trajectories_model.csv"):
        assert (sim / name).is_file(), name
    frame = pd.read_csv(sim / "trajectories.csv")
    assert list(frame.columns) == ["traj", "t", "node", "x", "y", "z"] and len(frame) == 2 * 6 * 10


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_trained_file_data_round_trip(tmp_path):
    # simulate → CSV → train on the file as measured data
    run_mpsim_ok(["simulate", "system=pendulum2", "format=csv", "n=9", "data.horizon=10"], tmp_path)
    (sim,) = _runs(tmp_path, "simulate")
    run_mpsim_ok(["train", f"data.path={sim / 'trajectories.csv'}", *TINY_TRAIN, "eval.plots=false"], tmp_path)
    summary = json.loads((_runs(tmp_path)[-1] / "summary.json").read_text())
    assert (
        summary["data"]["source"].endswith("trajectories.csv") and summary["data"]["train"] == 7
    )  # 9 trajectories split 0.7/0.15/0.15 → 7/1/1
    assert sim.name.endswith("_pendulum2") and _runs(tmp_path)[-1].name.endswith("_trajectories")  # named by its data
    # eval of the trained model on the file: the test share by default (said so), every trajectory with [0,0,1]
    ckpt = f"init={_runs(tmp_path)[-1] / 'checkpoints' / 'best.ckpt'}"
    share = run_mpsim_ok(["eval", ckpt, f"data.path={sim / 'trajectories.csv'}", "eval.plots=false"], tmp_path)
    assert "1 test trajectories, N=2, 10 steps (the test share of the file's 9; data.split=[0,0,1]" in share.stdout
    every = ["eval", ckpt, f"data.path={sim / 'trajectories.csv'}", "data.split=[0,0,1]", "eval.plots=false"]
    assert "9 test trajectories, N=2, 10 steps\n" in run_mpsim_ok(every, tmp_path).stdout
    assert json.loads((_runs(tmp_path, "eval")[-1] / "summary.json").read_text())["data"]["n_test"] == 9


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_sweep_gives_every_job_its_own_directory(lorenz_ws):
    ws = lorenz_ws
    args = ["train", "-m", *TINY_TRAIN, "eval.plots=false", "system=lorenz10", "data.n_train=4,6"]
    proc = run_mpsim_ok([*args, "init=lorenz3.ckpt,null"], ws)
    jobs = sorted(p.parent for p in (ws / "outputs" / "multirun").rglob("summary.json"))
    assert len(jobs) == 4 and len({j.name for j in jobs}) == 4, proc.stderr
    modes = sorted(json.loads((j / "summary.json").read_text())["mode"] for j in jobs)
    assert modes == ["finetune", "finetune", "scratch", "scratch"]
    n_train = sorted(json.loads((j / "summary.json").read_text())["data"]["train"] for j in jobs)
    assert n_train == [4, 4, 6, 6]
    report = run_mpsim_ok(["report", "runs=[outputs/multirun]"], ws)
    assert "data.n_train" in report.stdout and "init" in report.stdout
    # the sweep ends with that table of its jobs (printed, not written: the sweep folder holds only its jobs)
    (sweep,) = {j.parent for j in jobs}
    table = proc.stdout[proc.stdout.index("# mpsim report") :]
    assert f"4 runs under {sweep.relative_to(ws)}." in table and "| data.n_train | init |" in table
    assert f"mpsim report runs='[{sweep.relative_to(ws)}]'" in table
    assert sorted(p.name for p in sweep.iterdir()) == ["0", "1", "2", "3", "multirun.yaml"]


@pytest.mark.slow
@pytest.mark.scaling  # processes started: .ci/run's `-m scaling` step
def test_joblib_launcher_runs_jobs_in_parallel_processes(tmp_path):
    # the launcher starts worker processes: a subprocess, so that they end with it
    proc = run_cli(
        [
            "train",
            "-m",
            "hydra/launcher=joblib",
            "hydra.launcher.n_jobs=2",
            "seed=0,1",
            *TINY_TRAIN,
            "eval.plots=false",
        ],
        tmp_path,
        check=True,
    )
    jobs = sorted(p.parent for p in (tmp_path / "outputs" / "multirun").rglob("summary.json"))
    assert len(jobs) == 2, proc.stderr
    assert sorted(json.loads((j / "summary.json").read_text())["seed"] for j in jobs) == [0, 1]
    # Hydra's joblib launcher announces its pool; the basic launcher would log "Launching 2 jobs locally"
    output = proc.stdout + proc.stderr
    assert "Joblib.Parallel(n_jobs=2" in output and "Launching 2 jobs locally" not in output, output[-3000:]


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_resume_after_interrupt_matches_an_uninterrupted_run(tmp_path, monkeypatch):
    from mpsim.training.trainer import Trainer

    args = ["train", "trainer=quick", "trainer.max_epochs=6", "trainer.progress=false", "eval.plots=false"]
    args += ["data.n_train=8", "data.n_val=4", "data.n_test=4", "data.horizon=10"]
    full_ws, cut_ws = tmp_path / "full", tmp_path / "cut"
    full_ws.mkdir(), cut_ws.mkdir()
    run_mpsim_ok(args, full_ws)

    train_epoch = Trainer._train_epoch

    def ctrl_c_in_epoch_3(self, model, data, opt, loss_fn, shuffle, epoch):
        if epoch == 3:  # after a few batches' worth of work: what Ctrl-C during epoch 3 raises
            raise KeyboardInterrupt
        return train_epoch(self, model, data, opt, loss_fn, shuffle, epoch)

    monkeypatch.setattr(Trainer, "_train_epoch", ctrl_c_in_epoch_3)
    cut = run_mpsim(args, cut_ws)
    monkeypatch.undo()
    assert cut.code == 130 and "resume=true" in cut.err, (cut.code, cut.err[-2000:])
    (cut_run,) = _runs(cut_ws) or [m.parent for m in (cut_ws / "outputs").rglob("metrics.csv")]
    assert len(pd.read_csv(cut_run / "metrics.csv")) == 3  # epochs 0..2 finished before the interrupt
    res = run_mpsim_ok([*args, "resume=true"], cut_ws)
    assert f"mpsim train: resuming {cut_run.relative_to(cut_ws)}" in res.err
    (full_run,), (cut_run,) = _runs(full_ws), _runs(cut_ws)
    cols = ["epoch", "train_loss", "val_error", "test_error", "lr"]
    a, b = pd.read_csv(full_run / "metrics.csv")[cols], pd.read_csv(cut_run / "metrics.csv")[cols]
    assert len(a) == 7
    pd.testing.assert_frame_equal(a, b)
    sa, sb = (json.loads((r / "summary.json").read_text()) for r in (full_run, cut_run))
    assert sa["min_test_error"] == sb["min_test_error"] and sa["test"]["rmse"] == sb["test"]["rmse"]


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_a_finished_run_trains_on_with_a_larger_max_epochs_and_matches_a_longer_run(tmp_path):
    """`resume=true trainer.max_epochs=6` finds the finished 3-epoch run (when it stops is not what it is) and
    trains it on: its curve is the 6-epoch run's, row for row."""
    args = ["train", "trainer=quick", "trainer.progress=false", "eval.plots=false", "export=false"]
    args += ["data.n_train=8", "data.n_val=4", "data.n_test=4", "data.horizon=10"]
    full_ws, short_ws = tmp_path / "full", tmp_path / "short"
    full_ws.mkdir(), short_ws.mkdir()
    run_mpsim_ok([*args, "trainer.max_epochs=6"], full_ws)
    run_mpsim_ok([*args, "trainer.max_epochs=3"], short_ws)
    res = run_mpsim_ok([*args, "trainer.max_epochs=6", "resume=true"], short_ws)
    assert "resuming after epoch 3" in res.err and "trainer.max_epochs 3 -> 6" in res.err, res.err[-2000:]
    (full_run,), (short_run,) = _runs(full_ws), _runs(short_ws)
    cols = ["epoch", "train_loss", "val_error", "test_error", "lr"]
    a, b = pd.read_csv(full_run / "metrics.csv")[cols], pd.read_csv(short_run / "metrics.csv")[cols]
    assert len(a) == 7
    pd.testing.assert_frame_equal(a, b)
    # the run's record says what it trained under now (a report shows 6 epochs), the rest as the run wrote it
    overrides = yaml.safe_load((short_run / ".hydra" / "overrides.yaml").read_text())
    assert "trainer.max_epochs=6" in overrides and "trainer.max_epochs=3" not in overrides
    assert overrides[:-1] == [a for a in args[1:] if a != "trainer.max_epochs=3"]
    assert yaml.safe_load((short_run / ".hydra" / "config.yaml").read_text())["trainer"]["max_epochs"] == 6


def _fails(args, cwd, match, code=2):
    before = {p for p in cwd.rglob("*") if p.is_file()}
    proc = run_mpsim(args, cwd)
    assert proc.code == code, (proc.code, proc.out[-2000:], proc.err[-2000:])
    lines = proc.error_lines()
    assert len(lines) == 1 and match in lines[0], proc.err
    assert "Traceback" not in proc.err
    new = {p for p in cwd.rglob("*") if p.is_file()} - before
    # nothing half-written: no results, no checkpoints, no partial data, no run directory
    assert not [p for p in new if "/.cache/" not in str(p)], new
    return proc


def test_an_interrupted_command_other_than_train_is_told_to_run_again_not_to_resume(tmp_path, monkeypatch):
    import mpsim.commands.simulate as simulate

    def ctrl_c(*args, **kwargs):  # what Ctrl-C raises inside the command
        raise KeyboardInterrupt

    monkeypatch.setattr(simulate, "simulate_truth", ctrl_c)
    cut = run_mpsim(["simulate", "n=2"], tmp_path)
    assert cut.code == 130 and "interrupted" in cut.err, (cut.code, cut.err[-2000:])
    assert "resume=true" not in cut.err and "run the same command again" in cut.err  # resume= is train's alone


@pytest.mark.slow  # 3–6 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_bad_inputs_end_with_one_clear_message(lorenz_ws, tmp_path):
    ws = lorenz_ws
    _fails(["train", "system=lorenz4"], ws, "Could not find 'system/lorenz4'")
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
    unknown = run_mpsim(["frobnicate"], ws)
    assert unknown.code == 2 and "unknown command 'frobnicate'" in unknown.err
    _fails(["train", "trainer.lrr=1"], ws, "Did you mean trainer.lr?")


def _entry_points() -> list[list[str]]:
    script = Path(sys.executable).with_name("mpsim")
    found = str(script) if script.is_file() else shutil.which("mpsim")
    assert found, "the `mpsim` console script is not installed (pip install -e .)"
    return [[found], [sys.executable, "-m", "mpsim"]]


@pytest.mark.slow
@pytest.mark.scaling  # processes started: .ci/run's `-m scaling` step
def test_entry_points_exit_codes_and_stderr(tmp_path):
    """The installed `mpsim` script and `python -m mpsim` as a user runs them: real exit codes, one error line on
    stderr, no traceback, no files; and Ctrl-C (SIGINT) in a training run exits 130 with the resume hint."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    (tmp_path / "f").write_text("x")
    for entry in _entry_points():
        ok = subprocess.run([*entry, "--version"], cwd=tmp_path, capture_output=True, text=True, env=env)
        assert ok.returncode == 0 and ok.stdout.startswith("mpsim "), (entry, ok.stderr)
        for args, code, match in (
            (["frobnicate"], 2, "unknown command 'frobnicate'"),
            (["train", "trainer.lrr=1"], 2, "Did you mean trainer.lr?"),
        ):
            proc = subprocess.run([*entry, *args], cwd=tmp_path, capture_output=True, text=True, env=env)
            assert proc.returncode == code, (entry, args, proc.returncode, proc.stderr)
            lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("mpsim")]
            assert len(lines) == 1 and match in lines[0], (entry, proc.stderr)
            assert "Traceback" not in proc.stderr and proc.stdout == ""
            assert [p.name for p in tmp_path.iterdir()] == ["f"]
        unwritable = subprocess.run(
            [*entry, "train", "paths.output_root=f/o"], cwd=tmp_path, capture_output=True, text=True, env=env
        )
        assert unwritable.returncode == 4 and "is a file, not a directory" in unwritable.stderr
        assert [p.name for p in tmp_path.iterdir()] == ["f"]

    # Ctrl-C: far more epochs than can finish, so the signal always lands in a running training loop
    args = ["train", "trainer=quick", "trainer.max_epochs=100000", "trainer.early_stop_patience=0"]
    args += ["trainer.progress=false", "data.n_train=8", "data.n_val=4", "data.n_test=4", "data.horizon=10"]
    # as from a terminal: Ctrl-C at its default action, whatever this process inherited (a test run started in the
    # background, e.g. `nohup ... &`, ignores SIGINT, and an ignored signal stays ignored across exec)
    proc = subprocess.Popen(
        [*_entry_points()[0], *args],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        deadline = time.time() + 120
        while time.time() < deadline and proc.poll() is None:
            metrics = list((tmp_path / "outputs").rglob("metrics.csv"))
            if metrics and len(metrics[0].read_text().splitlines()) >= 3:  # header + epochs 0..1
                break
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        try:  # generous: under a loaded test run a tiny epoch can take seconds; exit comes within one
            _, err = proc.communicate(timeout=180)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate()
            pytest.fail(f"mpsim train still ran 180 s after SIGINT; its stderr ends:\n{err[-3000:]}")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130 and "interrupted" in err and "resume=true" in err, (proc.returncode, err[-2000:])
    assert "Traceback" not in err


def test_bench_writes_table_and_plot(tmp_path):
    run_mpsim_ok(["bench", "bench.nodes=[2,4]", "bench.batches=[1,2]", "bench.steps=3", "bench.repeats=1"], tmp_path)
    (run,) = sorted(p.parent for p in (tmp_path / "outputs" / "bench").rglob("bench.md"))
    assert "fwd_bwd_s" in (run / "bench.md").read_text() and (run / "plots" / "mpnode_scaling.png").is_file()


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_simulate_applies_data_burn_in_as_train_does(tmp_path):
    # data.burn_in was ignored by mpsim simulate (its files began at t=0 while train's data began after the burn-in)
    args = ["simulate", "system=pendulum2", "n=2", "format=npz", "eval.plots=false"]
    run_mpsim_ok([*args, "data.horizon=30", "data.burn_in=20", "hydra.run.dir=burn"], tmp_path)
    run_mpsim_ok([*args, "data.horizon=50", "hydra.run.dir=long"], tmp_path)
    with (
        np.load(tmp_path / "burn" / "trajectories.npz") as burn,
        np.load(tmp_path / "long" / "trajectories.npz") as long,
    ):
        assert burn["x"].shape == (2, 31, 2, 2) and burn["t"][0] == pytest.approx(20 * 0.1)
        assert np.allclose(burn["x"][:, 0], long["x"][:, 20], atol=1e-9)  # the record starts 20 steps in
    _fails(["simulate", "system=nbody20", "n=2", "data.horizon=3", "data.burn_in=5"], tmp_path, "has no burn-in")


# ---- mpsim <command> --help ----------------------------------------------------------------------------------
@pytest.mark.parametrize("command", ["train", "eval", "simulate", "diagnose", "report", "bench"])
def test_command_help_is_mpsims_own(command, tmp_path):
    for flag in ("--help", "-h"):
        res = run_mpsim([command, "system=lorenz3", flag] if command == "train" else [command, flag], tmp_path)
        assert res.code == 0 and res.err == "", res.err
        text = res.out
        assert text.startswith(f"usage: mpsim {command} ") and "_target_" not in text  # not Hydra's config dump
        assert f"mpsim {command} --cfg job" in text and f"mpsim {command} --hydra-help" in text
        assert text.count(f"\n  mpsim {command} ") == 3  # three examples
        assert max(len(line) for line in text.splitlines()) <= 100
    assert not list(tmp_path.iterdir())  # no run directory


def test_train_help_names_the_keys_a_newcomer_needs_and_every_group_option(tmp_path):
    from mpsim.cli import CONF_DIR

    text = run_mpsim(["train", "--help"], tmp_path).out
    keys = ["system=", "model=", "init=", "mode=", "resume=", "data.path=", "trainer.max_epochs=", "trainer.lr="]
    assert all(f"\n  {k}" in text for k in keys), text
    listed = " ".join(text.split("config groups")[1].split("examples:")[0].split())
    words = set(re.findall(r"[\w.]+", listed))
    assert {p.stem for p in (Path(CONF_DIR) / "system").glob("*.yaml")} <= words  # read from conf/
    assert "pendulum2 (default)" in listed and "hparams_search mpnode_lorenz10; none by default" in listed


def test_help_of_a_group_option_added_to_conf_is_listed(tmp_path, monkeypatch):
    import mpsim.cli as cli

    conf = tmp_path / "conf"
    shutil.copytree(cli.CONF_DIR, conf)
    (conf / "system" / "my_system.yaml").write_text("_target_: my_pkg.MySystem\n")
    monkeypatch.setattr(cli, "CONF_DIR", str(conf))
    assert "my_system" in run_mpsim(["train", "--help"], tmp_path).out


def test_hydra_help_and_cfg_job_still_reach_hydra(tmp_path):
    assert "== Flags ==\n--help,-h : Application's help" in run_mpsim(["train", "--hydra-help"], tmp_path).out
    assert "_target_: mpsim.training.trainer.Trainer" in run_mpsim(["train", "--cfg", "job"], tmp_path).out


def test_command_help_is_quick_and_imports_neither_torch_nor_hydra(tmp_path):
    code = (
        "import sys, time; t0 = time.perf_counter(); from mpsim.cli import main\n"
        "for c in ['train', 'eval', 'simulate', 'diagnose', 'report', 'bench']:\n"
        "    main([c, '--help'])\n"
        "took = time.perf_counter() - t0\n"
        "assert 'torch' not in sys.modules and 'hydra' not in sys.modules, 'help imported torch or hydra'\n"
        "print(f'took {took:.3f} s')\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    took = float(proc.stdout.split("took ")[-1].split()[0])
    assert took < 1.0, took  # all six, with mpsim's import (about 0.2 s on an idle core)


# ---- progress without a terminal -------------------------------------------------------------------------------
def test_output_redirected_to_a_file_gets_log_lines_not_a_progress_bar(tmp_path):
    # in this process stdout and stderr are not terminals, as with `mpsim train > log.txt 2>&1`: the bar used to
    # write one long line of carriage returns there
    args = [a for a in TINY_TRAIN if not a.startswith("trainer.progress")]
    res = run_mpsim_ok(["train", *args, "eval.plots=false", "trainer.progress=true", "trainer.log_every=2"], tmp_path)
    assert "\r" not in res.err + res.out and "epoch/s" not in res.err
    lines = [ln for ln in res.err.splitlines() if ln.startswith("epoch ")]
    assert [ln.split(":")[0] for ln in lines] == ["epoch 2/3"], res.err
