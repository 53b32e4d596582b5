"""Atomic file writes: readers (and concurrent sweep jobs) never see half a file."""

from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch


def atomic_write(path: str | Path, write: Any, mode: str = "wb") -> Path:
    """Write through a temporary sibling file and `os.replace` it into place.

    Args:
        path: destination.
        write: callable receiving the open temporary file object.
        mode: "wb" or "w".
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode) as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def json_default(obj: Any) -> Any:
    """`json.dump` fallback for tensors, arrays and numpy scalars."""
    if isinstance(obj, torch.Tensor | np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON-serialisable: {type(obj).__name__}")


def _clean(obj: Any) -> Any:
    """NaN/inf become null so that the JSON is standard."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_clean(v) for v in obj]
    return obj


def write_json(path: str | Path, data: Any) -> Path:
    """Write `data` as indented standard JSON (NaN → null), atomically."""
    text = json.dumps(_clean(json.loads(json.dumps(data, default=json_default))), indent=2)
    return atomic_write(path, lambda f: f.write(text + "\n"), mode="w")
