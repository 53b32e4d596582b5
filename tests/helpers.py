"""Helpers shared by the tests (conftest.py holds only fixtures): tiny configs, composing a command's config,
and running `mpsim` in this process (the default) or in a subprocess (the real entry point)."""

from __future__ import annotations

import contextlib
import io
import logging
import os
import random
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig

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


def make_cfg(command: str, overrides: list[str], tmp: Path):
    """Compose `command`'s config as the CLI would, with outputs, checkpoints and cache under `tmp`."""
    register_schemas()
    GlobalHydra.instance().clear()
    paths = [f"paths.output_root={tmp}/outputs", f"paths.ckpt_dir={tmp}/checkpoints", f"paths.cache_dir={tmp}/cache"]
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name=command, overrides=[*paths, *overrides])


def reset_hydra() -> None:
    """Forget Hydra's global state (the config search path and the running job's config)."""
    GlobalHydra.instance().clear()
    HydraConfig.instance().cfg = None


@dataclass
class Result:
    """What `mpsim <args>` left: its exit code, stdout and stderr."""

    code: int
    out: str
    err: str

    def error_lines(self) -> list[str]:
        return [ln for ln in self.err.splitlines() if ": error:" in ln]

    @property
    def returncode(self) -> int:  # the name `subprocess.CompletedProcess` uses
        return self.code

    @property
    def stdout(self) -> str:
        return self.out

    @property
    def stderr(self) -> str:
        return self.err


@contextlib.contextmanager
def process_state_restored() -> Iterator[None]:
    """Undo, on exit, what a command run in this process may change: cwd, argv, environment, umask, torch's
    default dtype and thread count, random generators, logging handlers and levels, Hydra's global state."""
    cwd, argv, env = os.getcwd(), list(sys.argv), dict(os.environ)
    umask = os.umask(0o022)
    os.umask(umask)
    dtype, threads = torch.get_default_dtype(), torch.get_num_threads()
    rng = (random.getstate(), np.random.get_state(), torch.get_rng_state())
    manager = logging.Logger.manager
    loggers = [logging.getLogger(), *(lg for lg in manager.loggerDict.values() if isinstance(lg, logging.Logger))]
    saved = {lg: (list(lg.handlers), lg.level, lg.propagate, lg.disabled) for lg in loggers}
    disable = logging.root.manager.disable
    try:
        yield
    finally:
        reset_hydra()
        os.chdir(cwd)
        sys.argv[:] = argv
        os.environ.clear()
        os.environ.update(env)
        os.umask(umask)
        torch.set_default_dtype(dtype)
        torch.set_num_threads(threads)
        random.setstate(rng[0])
        np.random.set_state(rng[1])
        torch.set_rng_state(rng[2])
        for lg in [logging.getLogger(), *manager.loggerDict.values()]:
            if not isinstance(lg, logging.Logger):
                continue
            handlers, level, propagate, disabled = saved.get(lg, ([], logging.NOTSET, True, False))
            for h in lg.handlers:
                if h not in handlers:
                    h.close()
            lg.handlers[:] = handlers
            lg.setLevel(level)
            lg.propagate, lg.disabled = propagate, disabled
        logging.disable(disable)


def run_mpsim(args: list[str], cwd: Path) -> Result:
    """`mpsim <args>` started from `cwd`, in this process (`mpsim.cli.main`), with its exit code (from
    `SystemExit`; 0 when it returns), stdout and stderr. Exceptions that are bugs propagate, as the traceback
    a user would see (exit code 1). Nothing it changes in the process outlives the call."""
    from mpsim import cli

    out, err = io.StringIO(), io.StringIO()
    code = 0
    with process_state_restored(), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        os.chdir(cwd)
        sys.argv[:] = ["mpsim", *args]
        try:
            cli.main(list(args))
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    return Result(code, out.getvalue(), err.getvalue())


def run_mpsim_ok(args: list[str], cwd: Path) -> Result:
    """`run_mpsim` that must succeed."""
    res = run_mpsim(args, cwd)
    if res.code != 0:
        raise AssertionError(f"mpsim {' '.join(args)} failed ({res.code}):\n{res.out[-3000:]}\n{res.err[-3000:]}")
    return res


def run_cli(args: list[str], cwd: Path, timeout: float = 300, check: bool = False) -> subprocess.CompletedProcess:
    """Run `mpsim <args>` in a subprocess started from `cwd` (for launchers that start processes, torchrun, and
    the real entry point's exit codes)."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "HYDRA_FULL_ERROR": "0"}
    proc = subprocess.run(
        [sys.executable, "-m", "mpsim.cli", *args], cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env
    )
    if check and proc.returncode != 0:
        raise AssertionError(f"mpsim {' '.join(args)} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
    return proc


def declared_pendulums(train):
    """The scientist's model of the pendulum pair: the declared (undamped) equations, g and k learnable, float64,
    normalised on `train` (the residual loop's white-box test model)."""
    from mpsim.models.physics import PhysicsModel
    from mpsim.solvers import ODESolver
    from mpsim.systems import CoupledPendulums

    model = PhysicsModel(
        2, system=CoupledPendulums(), learnable=["gravity", "spring"], solver=ODESolver("dopri5", rtol=1e-7, atol=1e-7)
    ).double()
    model.set_normalisation(train.x.reshape(-1, 2).mean(0), train.x.reshape(-1, 2).std(0))
    return model


# ---- the cli/ recipes with a stub `mpsim` ----------------------------------------------------------------------
_RECIPE_STUB = """#!/usr/bin/env bash
# stub mpsim: log the call; leave what a run (summary.json) or a report (its files) leaves in hydra.run.dir= or resume=,
# and the exported <system>.ckpt a run leaves in paths.ckpt_dir=
echo "$*" >> "$STUB_LOG"
ckpt_dir=; system=
for a in "$@"; do
  case $a in
    hydra.run.dir=*|resume=*)
      d=${a#*=}; mkdir -p "$d" && echo '{}' > "$d/summary.json"
      for f in report.md report.csv table1.png table2.png curves.png message_size.png message_size_curves.png messages.png; do
        : > "$d/$f"
      done;;
    paths.ckpt_dir=*) ckpt_dir=${a#*=};;
    system=*) system=${a#*=};;
  esac
done
if [ -n "$ckpt_dir" ] && [ -n "$system" ] && [[ $system != *,* ]]; then mkdir -p "$ckpt_dir" && : > "$ckpt_dir/$system.ckpt"; fi
# STUB_SLOW=<text>: a call whose arguments hold <text> takes STUB_SLOW_S seconds and logs "finished ..." at its end
if [ -n "${STUB_SLOW:-}" ] && [[ " $* " == *"$STUB_SLOW"* ]]; then sleep "${STUB_SLOW_S:-4}"; echo "finished $*" >> "$STUB_LOG"; fi
"""


def run_recipe(recipe: str, tmp: Path, **env: str) -> tuple[subprocess.CompletedProcess, list[list[str]]]:
    """Run `cli/<recipe>` with OUT=tmp/<recipe> and `mpsim` replaced on PATH by a stub that only logs its arguments,
    so a recipe's settings can be checked without training. Returns the process and the `mpsim` calls it made."""
    bin_dir = tmp / "stub_bin"
    bin_dir.mkdir(exist_ok=True)
    (bin_dir / "mpsim").write_text(_RECIPE_STUB)
    (bin_dir / "mpsim").chmod(0o755)
    log = tmp / f"{recipe}.calls"
    log.unlink(missing_ok=True)
    environ = {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}", "STUB_LOG": str(log), "OUT": str(tmp / recipe)}
    script = Path(__file__).resolve().parents[1] / "cli" / recipe
    proc = subprocess.run(["bash", str(script)], env={**environ, **env}, capture_output=True, text=True, timeout=120)
    return proc, [line.split() for line in log.read_text().splitlines()] if log.exists() else []


def inline_specs(cfg) -> None:
    """`system.spec=<file>` / `model.spec=<file>` replaced by the file's content, as `mpsim.commands.prepare` does
    (relative paths from the current directory)."""
    from omegaconf import DictConfig, open_dict

    from mpsim.spec import load_spec_file

    for key in ("system", "model"):
        node = cfg.get(key)
        if isinstance(node, DictConfig) and isinstance(node.get("spec"), str):
            with open_dict(cfg):
                node.spec = load_spec_file(Path(node.spec).expanduser())
