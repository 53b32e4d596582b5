"""Value checks every command relies on (ranges, choices, finiteness), made without importing torch."""

from __future__ import annotations

import math
from typing import Any

from omegaconf import DictConfig, OmegaConf

from mpsim.errors import ConfigError
from mpsim.process import DEVICE

_FINITE_GROUPS = ("system", "model", "solver", "trainer", "data", "eval")


def _check(ok: bool, message: str) -> None:
    if not ok:
        raise ConfigError(message)


def _nonfinite(node: Any, where: str, allow_inf: bool) -> str | None:
    """The first key under `node` holding NaN (or ±inf unless `allow_inf`), as `key=value`."""
    if isinstance(node, dict):
        for key, value in node.items():
            found = _nonfinite(value, f"{where}.{key}", allow_inf)
            if found:
                return found
    elif isinstance(node, list | tuple):
        for i, value in enumerate(node):
            found = _nonfinite(value, f"{where}[{i}]", allow_inf)
            if found:
                return found
    elif isinstance(node, float) and (math.isnan(node) or (math.isinf(node) and not allow_inf)):
        return f"{where}={node}"
    return None


def validate_values(cfg: DictConfig) -> None:
    """Check the values every command relies on (ranges, choices, finiteness) without importing torch.

    Raises:
        ConfigError: the first value that is out of range, naming the key, the rule and the fix.
    """
    if "device" in cfg:
        _check(
            bool(DEVICE.fullmatch(str(cfg.device))),
            f"device={cfg.device} is not supported; choose auto, cpu, cuda, cuda:<index> or mps.",
        )
    if cfg.get("threads") is not None:
        _check(
            cfg.threads >= 1,
            f"threads={cfg.threads}: give a number of CPU threads >= 1, or threads=null for torch's default.",
        )
    for group in _FINITE_GROUPS:
        if cfg.get(group) is None:
            continue
        try:
            node = OmegaConf.to_container(cfg[group], resolve=True)
        except Exception:  # noqa: BLE001 - unresolvable interpolations are reported where they are used
            continue
        bad = _nonfinite(node, group, allow_inf=group in ("trainer", "model", "solver"))
        _check(bad is None, f"{bad} is not a finite number; give a finite value for {str(bad).split('=')[0]}.")
    data = cfg.get("data")
    if data is not None:
        _check(
            data.noise_std >= 0,
            f"data.noise_std={data.noise_std}: noise is a standard deviation (in units of each "
            "feature's std); give a value >= 0 (0: no noise).",
        )
        for key in ("n_train", "n_val", "n_test"):
            _check(data[key] >= 1, f"data.{key}={data[key]}: each split needs at least 1 trajectory.")
        _check(data.burn_in >= 0, f"data.burn_in={data.burn_in}: give a number of steps >= 0.")
        _check(data.dt is None or data.dt > 0, f"data.dt={data.dt}: the sampling step must be > 0 (or null).")
        _check(
            data.get("resample") is None or data.resample > 0,
            f"data.resample={data.get('resample')}: give a step in seconds > 0 (or null: use each file's own grid).",
        )
        _check(
            data.get("segment") is None or data.segment > 0,
            f"data.segment={data.get('segment')}: give a length in seconds > 0 (or null: whole recordings).",
        )
        _check(data.get("stride", 1) >= 1, f"data.stride={data.get('stride')}: keep every k-th sample, k >= 1.")
        _check(data.horizon is None or data.horizon >= 1, f"data.horizon={data.horizon}: give >= 1 step (or null).")
        _check(data.gt_rtol > 0 and data.gt_atol > 0, "data.gt_rtol and data.gt_atol must be > 0.")
    ev = cfg.get("eval")
    if ev is not None:
        bad_h = [h for h in ev.horizons if h < 1]
        _check(not bad_h, f"eval.horizons={list(ev.horizons)}: horizons are numbers of steps >= 1; remove {bad_h}.")
    trainer = cfg.get("trainer")
    if trainer is not None:
        _validate_trainer(trainer)
    if "n" in cfg and cfg.get("task") == "simulate":
        _check(cfg.n >= 1, f"n={cfg.n}: simulate at least 1 trajectory.")


def _validate_trainer(t: DictConfig) -> None:
    rules = [
        ("max_epochs", lambda v: v >= 0, ">= 0"),
        ("batch_size", lambda v: v >= 1, ">= 1"),
        ("eval_batch_size", lambda v: v >= 1, ">= 1"),
        ("lr", lambda v: 0 < v < math.inf, "> 0 and finite"),
        ("weight_decay", lambda v: v >= 0, ">= 0"),
        ("clip_norm", lambda v: v >= 0, ">= 0 (0: no clipping)"),
        ("huber_delta", lambda v: v > 0, "> 0"),
        ("plateau_patience", lambda v: v >= 0, ">= 0"),
        ("plateau_factor", lambda v: 0 < v < 1, "between 0 and 1"),
        ("min_lr", lambda v: v >= 0, ">= 0"),
        ("early_stop_patience", lambda v: v >= 0, ">= 0 (0: never stop early)"),
        ("log_every_s", lambda v: v >= 0, ">= 0 seconds (0: never)"),
        ("log_every", lambda v: v >= 0, ">= 0 epochs (0: never)"),
        ("window", lambda v: v is None or v >= 1, ">= 1 step, or null"),
        ("eval_window", lambda v: v is None or v >= 1, ">= 1 step, or null"),
    ]
    for key, ok, rule in rules:
        if key in t and isinstance(t[key], int | float | type(None)) and not ok(t[key]):
            raise ConfigError(f"trainer.{key}={t[key]}: must be {rule}.")
