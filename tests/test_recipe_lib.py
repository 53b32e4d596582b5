"""cli/lib.sh, the paper recipes' resumable-run helper: train_once keeps, resumes or starts a run, and two
processes that reach the same run never train it at once (the second waits, then keeps what the first left).

`mpsim` is replaced on PATH by a stub that logs its arguments, takes a moment, and writes what a run writes."""

import os
import shutil
import subprocess
import textwrap
import time
from pathlib import Path

import pytest

LIB = Path(__file__).resolve().parents[1] / "cli" / "lib.sh"

pytestmark = pytest.mark.skipif(shutil.which("flock") is None, reason="needs flock (util-linux)")

STUB = textwrap.dedent(
    """\
    #!/usr/bin/env bash
    # stub mpsim: log the call, work for a moment, then leave a finished run in hydra.run.dir= or resume=
    echo "$*" >> "$STUB_LOG"
    sleep "${STUB_SLEEP:-0}"
    for a in "$@"; do
      case $a in hydra.run.dir=*|resume=*) d=${a#*=}; mkdir -p "$d" && echo '{}' > "$d/summary.json";; esac
    done
    exit "${STUB_RC:-0}"
    """
)


@pytest.fixture
def env(tmp_path):
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    stub = bin_dir / "mpsim"
    stub.write_text(STUB)
    stub.chmod(0o755)
    log = tmp_path / "calls.log"
    return {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}", "STUB_LOG": str(log)}, log


def train_once(env, run_dir, *args, wait=True):
    cmd = f"set -euo pipefail; source '{LIB}'; train_once '{run_dir}' {' '.join(args)}"
    p = subprocess.Popen(["bash", "-c", cmd], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    if not wait:
        return p
    out, _ = p.communicate(timeout=60)
    return p.returncode, out


def calls(log):
    return log.read_text().splitlines() if log.exists() else []


def test_fresh_then_kept(env, tmp_path):
    environ, log = env
    run = tmp_path / "runs" / "a"
    rc, _ = train_once(environ, run, "seed=0")
    assert rc == 0 and calls(log) == [f"train seed=0 hydra.run.dir={run}"]
    rc, out = train_once(environ, run, "seed=0")
    assert rc == 0 and "kept (finished)" in out and len(calls(log)) == 1


def test_interrupted_run_is_resumed(env, tmp_path):
    environ, log = env
    run = tmp_path / "a"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "last.ckpt").write_bytes(b"x")
    rc, out = train_once(environ, run, "seed=1")
    assert rc == 0 and "resuming" in out and calls(log) == [f"train seed=1 resume={run}"]


def test_device_is_passed_to_fresh_and_resumed_runs_only_when_set(env, tmp_path):
    environ, log = env
    cut = tmp_path / "cut"
    (cut / "checkpoints").mkdir(parents=True)
    (cut / "checkpoints" / "last.ckpt").write_bytes(b"x")
    assert train_once({**environ, "DEVICE": "cpu"}, cut, "seed=1")[0] == 0  # begun on a GPU, resumed here
    assert train_once({**environ, "DEVICE": "cpu"}, tmp_path / "new", "seed=2")[0] == 0
    assert train_once(environ, tmp_path / "plain", "seed=3")[0] == 0
    assert calls(log) == [
        f"train seed=1 device=cpu resume={cut}",
        f"train seed=2 device=cpu hydra.run.dir={tmp_path / 'new'}",
        f"train seed=3 hydra.run.dir={tmp_path / 'plain'}",
    ]


def test_failure_is_passed_on(env, tmp_path):
    environ, log = env
    rc, _ = train_once({**environ, "STUB_RC": "3"}, tmp_path / "a", "seed=0")
    assert rc == 3 and len(calls(log)) == 1


def test_two_processes_on_one_run_train_it_once(env, tmp_path):
    environ, log = env
    run = tmp_path / "a"
    slow = {**environ, "STUB_SLEEP": "2"}
    first = train_once(slow, run, "seed=0", wait=False)
    for _ in range(100):  # until the first has started its run (holds the lock)
        if calls(log):
            break
        time.sleep(0.05)
    second = train_once(slow, run, "seed=0", wait=False)
    out1, _ = first.communicate(timeout=60)
    out2, _ = second.communicate(timeout=60)
    assert first.returncode == second.returncode == 0
    assert len(calls(log)) == 1, calls(log)  # without the lock the second would start the same run again
    assert "waiting" in out2 and "kept (finished)" in out2
