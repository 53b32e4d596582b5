"""The `init=` checkpoint: finding it, loading it with its `_target_` allowlist, checking that it fits the data and
the model (naming the config key that differs). What a run's own checkpoints hold: `mpsim.training.checkpoint`.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from mpsim.commands.runtime import Runtime, resolve_path
from mpsim.errors import CheckpointError, IncompatibleError
from mpsim.models.base import Model
from mpsim.safeload import not_a_regular_file
from mpsim.training.checkpoint import config_targets, load_checkpoint

log = logging.getLogger(__name__)

# the data metadata a checkpoint keeps ("system"): first the keys that name the system and its shape, which mpsim
# reads back (`system` and `state_names` in messages, `n_nodes` for models tied to one graph size), then the rest
# within the budget
META_READ_BACK = ("system", "system_class", "state_names", "control_names", "n_nodes", "dt")
META_BUDGET = 64_000  # bytes of JSON; best.ckpt, last.ckpt (rewritten every epoch) and the export each hold it


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


def load_init(init: str | None, rt: Runtime, ckpt_dir: str, model_config: Any = None) -> dict[str, Any] | None:
    """The checkpoint `init=` names (None without one), loaded safely: its `_target_`s may be mpsim's classes and
    those the command's own model config (`model_config`, plain data) names, e.g. `model._target_=...`."""
    if not init:
        return None
    path = resolve_init(str(init), rt, ckpt_dir)
    allowed = config_targets(model_config) if model_config is not None else set()
    ckpt = load_checkpoint(path, allowed, need_config=True)
    log.info(f"init: {path}")
    return ckpt


def load_weights(model: Model, ckpt: dict[str, Any], model_cfg: dict[str, Any]) -> None:
    """Load checkpoint weights, naming the config key that makes them not fit."""
    own = model.state_dict()
    check_weights_fit(own, ckpt, model_cfg)
    state = ckpt["model"]["state_dict"]
    model.load_state_dict({k: v.to(own[k]) for k, v in state.items() if k in own}, strict=False)


def check_weights_fit(own: Mapping[str, torch.Tensor], ckpt: dict[str, Any], model_cfg: dict[str, Any]) -> None:
    """Refuse a checkpoint whose weights do not fit the model `model_cfg` builds.

    Args:
        own: the built model's state_dict; tensors on the meta device serve (only shapes are compared), so this
            runs before the model is allocated.
        ckpt: the loaded checkpoint.
        model_cfg: the config the model was built from (the checkpoint's with command-line overrides).

    Raises:
        CheckpointError: names the `model.*` override(s) that differ from the checkpoint's config or, when the
            checkpoint's own config does not describe its weights (e.g. `hidden` altered in the file), the
            first tensor and both shapes.
    """
    state = ckpt["model"]["state_dict"]
    mismatched = [k for k in state if k in own and state[k].shape != own[k].shape]
    # effects added on top of a checkpoint (e.g. by `mpsim diagnose fix=true`) start from their configured
    # coefficients; any other missing tensor means the architecture differs
    missing = [k for k in own if k not in state and not k.startswith("effects.")]
    if not mismatched and not missing:
        return
    saved_cfg = ckpt["model"]["config"]
    differ = [
        f"model.{k}: checkpoint {saved_cfg[k]!r}, config {model_cfg[k]!r}"
        for k in saved_cfg
        if k in model_cfg and saved_cfg[k] != model_cfg[k] and not k.startswith("_")
    ]
    if differ:
        raise CheckpointError(
            f"{ckpt['path']} does not fit this model ({'; '.join(differ)}). Drop the override(s) to use the "
            "checkpoint's architecture, or train from scratch without init=."
        )
    if mismatched:
        key = mismatched[0]
        detail = f"model.state_dict[{key!r}] is {list(state[key].shape)} but the config builds {list(own[key].shape)}"
    else:
        detail = f"model.state_dict lacks {missing[0]!r} ({list(own[missing[0]].shape)}), which the config builds"
    raise CheckpointError(
        f"{ckpt['path']}: its model.config does not describe its weights: {detail} ({len(mismatched) + len(missing)} "
        "tensor(s) differ). The file was altered or written by other code; use another copy, or retrain."
    )


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
