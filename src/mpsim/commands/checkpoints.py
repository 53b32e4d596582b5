"""Checkpoints at the command layer: finding `init=`, loading it with its `_target_` allowlist, checking that it fits
the data and the model (naming the config key that differs), and the static part of every checkpoint a run writes.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from mpsim.commands.runtime import Runtime, resolve_path
from mpsim.errors import CheckpointError, IncompatibleError
from mpsim.models.base import Model
from mpsim.safeload import not_a_regular_file
from mpsim.training.checkpoint import config_targets, load_checkpoint

log = logging.getLogger(__name__)


def resolve_init(init: str, rt: Runtime, ckpt_dir: str) -> Path:
    """Find `init=`: an absolute path, a path from the start directory, then a name in `paths.ckpt_dir`."""
    ckpt_root = resolve_path(ckpt_dir, rt.start_dir)
    candidates = [resolve_path(init, rt.start_dir), ckpt_root / init]
    if not init.endswith(".ckpt"):
        candidates.append(ckpt_root / f"{init}.ckpt")
    for candidate in candidates:
        if candidate.is_file():
            return candidate
        why = not_a_regular_file(candidate)
        if why is not None and why != "does not exist" and not candidate.is_dir():  # a pipe: never opened
            raise CheckpointError(f"init={init}: {candidate} {why}; point init= at a checkpoint file (.ckpt).")
    folder = next((c for c in candidates if c.is_dir()), None)
    if folder is not None:  # a run directory given for its model
        inside = [folder / "checkpoints" / name for name in ("best.ckpt", "last.ckpt")]
        found = [str(p) for p in inside if p.is_file()]
        hint = f"; a run's model is its checkpoints/best.ckpt: init={found[0]}" if found else ""
        raise CheckpointError(f"init={init}: {folder} is a folder, not a checkpoint file{hint}.")
    available = sorted(p.name for p in ckpt_root.glob("*.ckpt")) if ckpt_root.is_dir() else []
    listing = (
        f" Available in {ckpt_root}: {', '.join(available)}." if available else f" {ckpt_root} has no checkpoints."
    )
    looked = ", ".join(dict.fromkeys(map(str, candidates)))  # each place once
    raise CheckpointError(f"init={init}: no such checkpoint (looked for {looked}).{listing}")


def load_init(cfg: DictConfig, rt: Runtime) -> dict[str, Any] | None:
    if not cfg.init:
        return None
    path = resolve_init(str(cfg.init), rt, cfg.paths.ckpt_dir)
    # a checkpoint may name mpsim's classes, and those the user's own config names (e.g. model._target_=...)
    allowed = config_targets(OmegaConf.to_container(cfg.model, resolve=True)) if cfg.get("model") is not None else set()
    ckpt = load_checkpoint(path, allowed, need_config=True)
    log.info(f"init: {path}")
    return ckpt


def load_weights(model: Model, ckpt: dict[str, Any], model_cfg: dict[str, Any]) -> None:
    """Load checkpoint weights, naming the config key that makes them not fit."""
    state = ckpt["model"]["state_dict"]
    own = model.state_dict()
    mismatched = [k for k in state if k in own and state[k].shape != own[k].shape]
    # effects added on top of a checkpoint (e.g. by `mpsim diagnose fix=true`) start from their configured
    # coefficients; any other missing tensor means the architecture differs
    missing = [k for k in own if k not in state and not k.startswith("effects.")]
    if mismatched or missing:
        saved_cfg = ckpt["model"]["config"]
        differ = [
            f"model.{k}: checkpoint {saved_cfg[k]!r}, config {model_cfg[k]!r}"
            for k in saved_cfg
            if k in model_cfg and saved_cfg[k] != model_cfg[k] and not k.startswith("_")
        ]
        detail = "; ".join(differ) if differ else f"tensors {(mismatched + missing)[:3]} do not fit"
        raise CheckpointError(
            f"{ckpt['path']} does not fit this model ({detail}). Drop the override(s) to use the checkpoint's "
            "architecture, or train from scratch without init=."
        )
    model.load_state_dict({k: v.to(own[k]) for k, v in state.items() if k in own}, strict=False)


def check_checkpoint_system(ckpt: dict[str, Any], state_dim: int, control_dim: int, state_names: list[str]) -> None:
    """A checkpoint trained on D states per node cannot run on data with another D (or control count)."""
    meta = ckpt["system"]
    ck_d, ck_c = int(ckpt["model"]["state_dim"]), int(ckpt["model"].get("control_dim", 0))
    if ck_d != state_dim or ck_c != control_dim:
        if ck_d == state_dim:  # the node state matches: only the inputs differ, and the data are what is off
            fix = (
                f"Give the data the {ck_c} control inputs per node the model was trained with (`u` [B, T, N, "
                f"{ck_c}] in an .npz; data.control_columns=[...] for a CSV)"
                if ck_c
                else "This model takes no control inputs: drop `u` from the .npz (or data.control_columns)"
            )
        else:
            fix = "Use a checkpoint of a system with the same node state, or drop init="
        raise IncompatibleError(
            f"{ckpt['path']} was trained on {meta.get('system')} ({ck_d} states {meta.get('state_names')}, "
            f"{ck_c} controls per node) but this data has {state_dim} states {state_names} and {control_dim} "
            f"controls per node. {fix}."
        )


def checkpoint_base(
    model_cfg: dict[str, Any], model: Model, system_meta: dict[str, Any], extra: dict[str, Any] | None = None
) -> dict[str, Any]:
    """The static part of every checkpoint a run writes."""
    return {
        "model": {"config": model_cfg, "state_dim": model.state_dim, "control_dim": model.control_dim},
        "normalisation": {
            "mean": model.state_mean.detach().cpu().clone(),
            "std": model.state_std.detach().cpu().clone(),
        },
        "system": _plain(system_meta),
        **(extra or {}),
    }


def _plain(obj: Any) -> Any:
    """Metadata reduced to containers that `torch.load(weights_only=True)` accepts."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_plain(v) for v in obj]
    if obj is None or isinstance(obj, bool | int | float | str):
        return obj
    return str(obj)
