"""`mpsim eval init=<ckpt> system=<name>`: evaluate a checkpoint on a test split, without training."""

from __future__ import annotations

import time
from pathlib import Path

from omegaconf import DictConfig

from mpsim.commands.prepare import prepare
from mpsim.commands.scoring import eval_options, evaluate_checkpoint
from mpsim.errors import ConfigError


def run_eval(cfg: DictConfig, output_dir: str | Path | None = None, overrides: list[str] | None = None) -> dict:
    """Evaluate `init=` on the test split of `system=` (or of `data.path=`); write summary.json and plots.

    Nothing trains: a file's train and val shares may be zero (`data.split=[0,0,1]` evaluates every trajectory).
    """
    started = time.perf_counter()
    if not cfg.init:
        raise ConfigError("mpsim eval needs init=<checkpoint> (a path, or a name in paths.ckpt_dir).")
    job = prepare(cfg, "eval", output_dir, overrides)
    options = eval_options(cfg.eval)
    return evaluate_checkpoint(job, options, task="eval", started=started)
