"""Checkpoints: plain containers of tensors, written atomically, loaded with `weights_only=True`.

A checkpoint holds the model's config (with its `_target_`) and weights, the normalisation statistics,
the metadata of the system it was trained on and its metrics; `last.ckpt` also holds the trainer state
(optimiser, schedule, early stopping, RNG, history) so that `resume=true` continues exactly.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from mpsim.errors import CheckpointError
from mpsim.files import atomic_write

FORMAT = "mpsim-checkpoint"
VERSION = 1


def save_checkpoint(path: str | Path, payload: dict[str, Any]) -> Path:
    """Save `payload` (plain containers and tensors only) atomically."""
    payload = {"format": FORMAT, "version": VERSION, **payload}
    return atomic_write(path, lambda f: torch.save(payload, f))


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Load a checkpoint safely (`weights_only=True`) and check that it is an mpsim checkpoint.

    Raises:
        CheckpointError: missing, unreadable, or not an mpsim checkpoint.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist.")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - any unpickling failure means the same thing to the user
        raise CheckpointError(
            f"cannot read checkpoint {path}: {type(err).__name__}: {str(err).splitlines()[0][:200]}. "
            "It may be truncated or not an mpsim checkpoint; retrain or point init= at another file."
        ) from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not an mpsim checkpoint (no '{FORMAT}' header).")
    if payload.get("version", 0) > VERSION:
        raise CheckpointError(
            f"{path} was written by a newer mpsim (checkpoint version {payload['version']} > {VERSION}); upgrade mpsim."
        )
    for key in ("model", "normalisation", "system"):
        if key not in payload:
            raise CheckpointError(f"{path} lacks '{key}'; it is incomplete. Retrain to write a new one.")
    payload["path"] = str(path)
    return payload


def rng_state() -> dict[str, Any]:
    """Global torch RNG state (for an exact resume)."""
    return {"torch": torch.get_rng_state()}


def set_rng_state(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
