"""`mpsim eval init=<ckpt> system=<name>`: evaluate a checkpoint on a test split, without training."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from mpsim.commands.evaluation import evaluate_checkpoint
from mpsim.commands.runtime import setup_runtime
from mpsim.errors import ConfigError


def run_eval(cfg: DictConfig, output_dir: str | Path | None = None, overrides: list[str] | None = None) -> dict:
    """Evaluate `init=` on the test split of `system=` (or of `data.path=`); write summary.json and plots."""
    rt = setup_runtime(cfg, output_dir, overrides)
    if not cfg.init:
        raise ConfigError("mpsim eval needs init=<checkpoint> (a path, or a name in paths.ckpt_dir).")
    return evaluate_checkpoint(cfg, rt, task="eval")
