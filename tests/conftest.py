"""Shared fixtures: composed configs for the command functions, small systems, and a CLI runner."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

import mpsim
from mpsim.config import register_schemas

CONF_DIR = str(Path(mpsim.__file__).parent / "conf")
TINY_TRAIN = [
    "trainer=quick",
    "trainer.progress=false",
    "data.n_train=8",
    "data.n_val=4",
    "data.n_test=4",
    "data.horizon=10",
    "eval.horizons=[1,5,10]",
]


@pytest.fixture(autouse=True)
def _one_thread():
    # tiny tensors: one intra-op thread is fastest and keeps tests quiet on a shared 2-core machine
    torch.set_num_threads(1)
    yield


def make_cfg(command: str, overrides: list[str], tmp: Path):
    """Compose `command`'s config as the CLI would, with outputs, checkpoints and cache under `tmp`."""
    register_schemas()
    GlobalHydra.instance().clear()
    paths = [f"paths.output_root={tmp}/outputs", f"paths.ckpt_dir={tmp}/checkpoints", f"paths.cache_dir={tmp}/cache"]
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name=command, overrides=[*paths, *overrides])


@pytest.fixture
def cfg_factory(tmp_path):
    def factory(command: str, *overrides: str):
        return make_cfg(command, list(overrides), tmp_path)

    return factory


def run_cli(args: list[str], cwd: Path, timeout: float = 300, check: bool = False) -> subprocess.CompletedProcess:
    """Run `mpsim <args>` in a subprocess started from `cwd`."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "HYDRA_FULL_ERROR": "0"}
    proc = subprocess.run(
        [sys.executable, "-m", "mpsim.cli", *args], cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env
    )
    if check and proc.returncode != 0:
        raise AssertionError(f"mpsim {' '.join(args)} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
    return proc
