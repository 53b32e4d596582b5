"""A resumed training run: its `last.ckpt` loaded and checked, and the new stopping rule written into its record.

`resume=` (the CLI) points the run directory at the run it continues; `mpsim.commands.prepare` loads it here.
"""

from __future__ import annotations

import logging
from pathlib import Path

import torch
import yaml

from mpsim.config import read_overrides_file
from mpsim.errors import CheckpointError, DataError
from mpsim.files import atomic_write
from mpsim.safeload import RECORD_BYTES, load_yaml
from mpsim.training.checkpoint import load_checkpoint
from mpsim.training.trainer import check_resume

log = logging.getLogger(__name__)


def load_resumed(run_dir: Path, max_epochs: int, patience: int) -> dict:
    """`<run dir>/checkpoints/last.ckpt` of a run being resumed (the CLI points the run directory at it), checked:
    its trainer state whole, and the new budget (`max_epochs`, `patience`) not below what it has run."""
    last = run_dir / "checkpoints" / "last.ckpt"
    if not last.is_file():
        raise CheckpointError(
            f"resume: no {last}. Resume reruns the same command in the directory of the run it continues; "
            "pass resume=<run dir> to name it, or drop resume=true to start afresh."
        )
    state = load_checkpoint(last)
    if "trainer" not in state:
        raise CheckpointError(f"resume: {last} holds no trainer state.")
    check_trainer_state(state["trainer"], last)
    check_resume(state["trainer"], int(max_epochs), int(patience))
    return state


def record_stopping(run_dir: Path, stopping: dict[str, int]) -> None:
    """Write a resume's new `trainer.max_epochs` / `trainer.early_stop_patience` into the run's `.hydra/` record
    (overrides.yaml and config.yaml, atomically), so a report of the run shows the budget it trained under. The
    rest of the record stays as the run wrote it."""
    record = run_dir / ".hydra"
    try:
        config = load_yaml(record / "config.yaml", RECORD_BYTES, str(record / "config.yaml"), "Restore it")
        overrides = read_overrides_file(run_dir)
    except (OSError, UnicodeDecodeError, yaml.YAMLError, DataError):
        return  # no record to keep up to date (the CLI refused a damaged one and warned of a missing one)
    if not isinstance(config, dict) or not isinstance(config.get("trainer"), dict) or overrides is None:
        return
    changed = {key: int(value) for key, value in stopping.items() if config["trainer"].get(key) != int(value)}
    if not changed:
        return
    for key, value in changed.items():
        config["trainer"][key] = value
        kept = [o for o in overrides if str(o).split("=", 1)[0].lstrip("+~") != f"trainer.{key}"]
        overrides = [*kept, f"trainer.{key}={value}"]
    text = yaml.safe_dump(overrides, sort_keys=False)
    atomic_write(record / "overrides.yaml", lambda f: f.write(text), mode="w")
    config_text = yaml.safe_dump(config, sort_keys=False)
    atomic_write(record / "config.yaml", lambda f: f.write(config_text), mode="w")
    log.info(f"recorded {', '.join(f'trainer.{k}={v}' for k, v in changed.items())} in {record}")


#: what a resume reads from a last.ckpt's trainer state, and the type each must have
_TRAINER_STATE: dict[str, type | tuple[type, ...]] = {
    "epoch": int,
    "best_epoch": int,
    "since_best": int,
    "max_epochs": int,
    "best_val": (int, float),
    "model_state": dict,
    "best_state": dict,
    "optimizer": dict,
    "scheduler": dict,
    "history": list,
}


def check_trainer_state(trainer: dict, path: Path) -> None:
    """The counters and mappings a resume reads: present (`max_epochs` only in newer files), of their types, the
    counters >= 0 (one message naming the first that is wrong)."""

    for key, kind in _TRAINER_STATE.items():
        if key not in trainer:
            if key == "max_epochs":
                continue
            raise CheckpointError(f"resume: {path} lacks 'trainer.{key}'; the file is damaged. Start the run afresh.")
        value = trainer[key]
        if (
            isinstance(value, bool)
            or not isinstance(value, kind)
            or (kind is int and isinstance(value, int) and value < 0)
        ):
            raise CheckpointError(
                f"resume: {path}: 'trainer.{key}' is {value!r:.60}, not what a trainer writes "
                f"({'a count >= 0' if kind is int else 'a ' + getattr(kind, '__name__', 'number')}); the file is "
                "damaged. Start the run afresh."
            )
    if not isinstance(trainer.get("shuffle_rng"), torch.Tensor):
        raise CheckpointError(
            f"resume: {path} lacks the tensor 'trainer.shuffle_rng'; the file is damaged. Start the run afresh."
        )
