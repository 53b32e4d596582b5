"""Data-parallel training (DDP under torchrun): sharding arithmetic, rank-0-only files, and a 2-process CPU
(gloo) run that follows the 1-process loss curve, interrupted and resumed on the way."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
import torch

from mpsim.__main__ import worker_args
from mpsim.commands import train as train_command
from mpsim.commands.train import run_train
from mpsim.training import distributed
from mpsim.training.distributed import DistContext

# float64 and fixed-step rk4: the 2-process run then differs from one process only by the summation order of
# the gradient all-reduce (measured: ~1e-15 relative); 5 trajectories per batch of 12 gives uneven shards
# (3 + 2, and 1 + 1 for the last batch), 5 validation trajectories uneven evaluation shards, and 1 test
# trajectory an empty evaluation shard on rank 1
TINY_DDP = [
    "trainer=quick",
    "trainer.progress=false",
    "trainer.max_epochs=8",
    "trainer.batch_size=5",
    "data.n_train=12",
    "data.n_val=5",
    "data.n_test=1",
    "data.horizon=10",
    "solver=rk4",
    "dtype=float64",
    "export=false",
    "eval.plots=false",
    "eval.horizons=[1,5,10]",
]
RTOL = 1e-6  # the stated tolerance of 2-process vs 1-process curves (float64)


def test_shards_cover_the_batch_and_weights_restore_its_mean():
    idx = torch.arange(10, 17)  # 7 items over 3 ranks: 3 + 2 + 2
    parts = [DistContext(rank=r, world_size=3).shard(idx) for r in range(3)]
    assert torch.equal(torch.cat([p for p, _ in parts]), idx)
    # DDP averages the ranks' gradients: sum_r w_r * mean_r / P must be the mean over the whole batch
    values = torch.rand(7, dtype=torch.float64)
    means = [values[p - 10].mean() * w for p, w in parts]
    assert torch.isclose(sum(means) / 3, values.mean())
    # a batch smaller than the world: the idle rank runs one item with weight 0
    part, weight = DistContext(rank=2, world_size=3).shard(idx[:2])
    assert len(part) == 1 and weight == 0.0
    assert DistContext().shard(idx) == (idx, 1.0)


def test_non_zero_ranks_get_no_run_directory(monkeypatch):
    args = ["train", "system=lorenz3"]
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "0")
    assert worker_args(args) == args
    monkeypatch.setenv("RANK", "1")
    out = worker_args(args)
    assert out[:2] == args and {"hydra.output_subdir=null", "hydra/job_logging=none", "hydra.run.dir=."} <= set(out)
    resumed = worker_args([*args, "resume=true"])  # the ranks read the resumed run's last.ckpt
    assert "hydra.run.dir=." not in resumed and "hydra.output_subdir=null" in resumed


def test_ranks_leave_together_after_a_success_and_at_once_after_an_error(cfg_factory, monkeypatch):
    """gloo: a barrier before leaving the group after a success; none after an error (a rank that failed between
    collectives would leave the others waiting in it)."""
    calls: list[str] = []
    monkeypatch.setattr(distributed.torch_dist, "is_initialized", lambda: True)
    monkeypatch.setattr(distributed.torch_dist, "monitored_barrier", lambda timeout: calls.append("barrier"))
    monkeypatch.setattr(distributed.torch_dist, "destroy_process_group", lambda: calls.append("destroy"))
    two = DistContext(rank=1, world_size=2, backend="gloo")
    distributed.teardown(two)
    assert calls == ["barrier", "destroy"]
    calls.clear()
    distributed.teardown(DistContext(rank=1, world_size=2, backend="nccl"))  # no gloo threads to wait for
    assert calls == ["destroy"]
    calls.clear()
    distributed.teardown(two, together=False)
    assert calls == ["destroy"]
    distributed.teardown(DistContext())  # one process: no group to leave
    assert calls == ["destroy"]

    left: list[bool] = []
    monkeypatch.setattr(distributed, "setup", lambda device: two)
    monkeypatch.setattr(distributed, "teardown", lambda ctx, together=True: left.append(together))
    real_prepare = train_command.prepare  # the data and model as one process prepares them, in the fake group

    def prepare(*args, **kwargs):
        return dataclasses.replace(real_prepare(*args, **{**kwargs, "distributed_run": False}), dist=two)

    monkeypatch.setattr(train_command, "prepare", prepare)
    monkeypatch.setattr(train_command, "train", lambda job, *args: {"task": "train", "rank": job.dist.rank})
    run_train(cfg_factory("train", *TINY_DDP))
    monkeypatch.setattr(train_command, "train", lambda job, *args: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        run_train(cfg_factory("train", *TINY_DDP))
    assert left == [True, False]


PROBE = Path(__file__).with_name("ddp_exit_probe.py")  # `-m mpsim` that also records when each rank leaves


def _torchrun(args: list[str]) -> list[str]:
    return [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc_per_node=2",
        str(PROBE),
        "train",
        *args,
    ]


def _env(tmp_path: Path) -> dict[str, str]:
    (tmp_path / "exits").mkdir(exist_ok=True)
    return {
        **os.environ,
        "OMP_NUM_THREADS": "1",
        "PYTHONUNBUFFERED": "1",
        "MPSIM_EXIT_TIMES": str(tmp_path / "exits"),
    }


def _same_curve(reference: Path, run: Path, epochs: int) -> None:
    """The two runs' metrics.csv agree epoch by epoch (train loss, errors, learning rate) to RTOL."""
    cols = ["epoch", "train_loss", "val_error", "test_error", "lr"]
    a = pd.read_csv(reference / "metrics.csv")[cols]
    b = pd.read_csv(run / "metrics.csv")[cols]
    assert len(a) == len(b) == epochs + 1
    pd.testing.assert_frame_equal(a, b, check_exact=False, rtol=RTOL)


def _check_follows(ws, reference, one: dict, epochs: int, backend: str = "gloo") -> None:
    """`ws` holds exactly one 2-process run, and its curve is the 1-process run's (`reference`); its ranks left
    together (`distributed.teardown`): rank 1, which has nothing to do after training, waited for rank 0 to
    evaluate and write the run's files (the last is summary.json) before it went on to exit."""
    (run,) = (ws / "outputs" / "train").glob("*/*")  # rank 1 made no run directory of its own
    assert sorted(p.name for p in ws.iterdir()) == ["outputs"]  # nor any file where it started
    exits = ws.parent / "exits"
    assert float((exits / "rank1").read_text()) >= (run / "summary.json").stat().st_mtime
    summary = json.loads((run / "summary.json").read_text())
    assert summary["distributed"] == {"world_size": 2, "backend": backend}
    _same_curve(reference, run, epochs)
    assert summary["best_val_error"] == pytest.approx(one["best_val_error"], rel=RTOL)
    assert summary["test"]["rmse"] == pytest.approx(one["test"]["rmse"], rel=RTOL)


@pytest.mark.slow
@pytest.mark.scaling  # processes started: .ci/run's `-m scaling` step
def test_two_processes_follow_the_one_process_loss_curve(cfg_factory, tmp_path):
    args = [*TINY_DDP, "trainer.max_epochs=4"]
    one = run_train(cfg_factory("train", *args), output_dir=tmp_path / "one")
    ws = tmp_path / "ws"
    ws.mkdir()
    proc = subprocess.run(
        _torchrun([*args, f"paths.cache_dir={tmp_path}/cache"]),
        cwd=ws,
        env=_env(tmp_path),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    _check_follows(ws, tmp_path / "one", one, 4)


@pytest.mark.slow
@pytest.mark.scaling
def test_two_processes_resume_after_an_interrupt(cfg_factory, tmp_path):
    one = run_train(cfg_factory("train", *TINY_DDP), output_dir=tmp_path / "one")
    ws = tmp_path / "ws"
    ws.mkdir()
    args = [*TINY_DDP, f"paths.cache_dir={tmp_path}/cache"]
    proc = subprocess.Popen(
        _torchrun(args),
        cwd=ws,
        env=_env(tmp_path),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        metrics = list((ws / "outputs").rglob("metrics.csv"))
        if metrics and len(metrics[0].read_text().splitlines()) >= 4:  # header + epochs 0..2
            break
        time.sleep(0.02)
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)  # torchrun and both ranks, mid-run
    out, _ = proc.communicate(timeout=60)
    # never a skip: a run that finished first tested no resume (make TINY_DDP's epochs longer if this fails)
    assert proc.returncode != 0, "the 2-process run finished before it could be interrupted"
    assert list((ws / "outputs").rglob("last.ckpt")), out
    resumed = subprocess.run(
        _torchrun([*args, "resume=true"]), cwd=ws, env=_env(tmp_path), capture_output=True, text=True, timeout=300
    )
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    _check_follows(ws, tmp_path / "one", one, 8)


# the code paths that differ by device: the CPU's tanh as 2σ(2x) − 1 (torch's tanh elsewhere), mpsim's own dopri5
# (step control read back to the host), MP-NODE's dense adjacency product (graphs up to 128 nodes) and its
# edge-list scatter, L2S, and the quadrotors' controls
GPU_CASES = {
    "pendulum2 rk4": [],
    "quad3 dopri5 controls": ["system=quad3", "solver=dopri5"],
    "gene 8x8 dense product": ["system=gene_ba_large", "solver=dopri5"],
    "gene 8x8 edge list": ["system=gene_ba_large", "solver=dopri5", "model.dense_max_nodes=0"],
    "gene 8x8 L2S": ["system=gene_ba_large", "solver=dopri5", "model=l2s"],
}


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.parametrize("case", list(GPU_CASES))
def test_training_on_a_gpu_matches_the_cpu(cfg_factory, tmp_path, case):
    args = [*TINY_DDP, *GPU_CASES[case]]
    cpu = run_train(cfg_factory("train", *args, "device=cpu"), output_dir=tmp_path / "cpu")
    gpu = run_train(cfg_factory("train", *args, "device=cuda"), output_dir=tmp_path / "gpu")
    assert gpu["best_val_error"] == pytest.approx(cpu["best_val_error"], rel=RTOL)
    _same_curve(tmp_path / "cpu", tmp_path / "gpu", 8)


@pytest.mark.gpu
@pytest.mark.skipif(torch.cuda.device_count() < 2, reason="needs 2 CUDA GPUs")
def test_two_gpus_follow_the_one_process_loss_curve(cfg_factory, tmp_path):
    args = [*TINY_DDP, "trainer.max_epochs=4"]
    one = run_train(cfg_factory("train", *args, "device=cpu"), output_dir=tmp_path / "one")
    ws = tmp_path / "ws"
    ws.mkdir()
    proc = subprocess.run(
        _torchrun([*args, "device=cuda", f"paths.cache_dir={tmp_path}/cache"]),
        cwd=ws,
        env=_env(tmp_path),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    _check_follows(ws, tmp_path / "one", one, 4, backend="nccl")
