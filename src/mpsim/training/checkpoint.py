"""Checkpoints: plain containers of tensors, written atomically, loaded with `weights_only=True`.

A checkpoint holds the model's config (with its `_target_`) and weights, the normalisation statistics,
the metadata of the system it was trained on and its metrics; `last.ckpt` also holds the trainer state
(optimiser, schedule, early stopping, RNG, history) so that `resume=true` continues exactly.

A checkpoint is data, never code. Loading one checks, before anything is built from it:

- its structure (the keys and types every command relies on);
- a SHA-256 checksum of its content, stored when it was written (a flipped byte in a weight is refused,
  not reported later as a solver failure);
- that its weights and normalisation statistics are finite;
- that every `_target_` in its model config names an mpsim class (``mpsim.…``) or one the user named
  explicitly (`allowed_targets`, taken from the command line/config). A file cannot make `instantiate`
  call anything else (e.g. ``pathlib.Path.write_text``).
"""

from __future__ import annotations

import hashlib
import importlib
import inspect
import json
import logging
import re
import sys
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from mpsim.errors import CheckpointError
from mpsim.files import atomic_write
from mpsim.memory import fmt_bytes
from mpsim.models.base import Model
from mpsim.safeload import not_a_regular_file, parse_json

log = logging.getLogger(__name__)

FORMAT = "mpsim-checkpoint"
VERSION = 2  # 2: content checksum
_UNHASHED = ("checksum", "path")
_MPSIM_NAME = re.compile(r"mpsim(\.[A-Za-z_][A-Za-z0-9_]*)+")


def content_checksum(payload: dict[str, Any]) -> str:
    """SHA-256 over every tensor (name, dtype, shape, bytes) and plain value of `payload`, in a fixed order."""
    digest = hashlib.sha256()
    _feed(digest, "", {k: v for k, v in payload.items() if k not in _UNHASHED})
    return digest.hexdigest()


def _feed(digest: Any, where: str, obj: Any) -> None:
    if isinstance(obj, torch.Tensor):
        t = obj.detach().cpu().contiguous()
        digest.update(f"{where}|T|{t.dtype}|{tuple(t.shape)}|".encode())
        digest.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    elif isinstance(obj, dict):
        for key in sorted(obj, key=str):
            _feed(digest, f"{where}/{key}", obj[key])
    elif isinstance(obj, list | tuple):
        digest.update(f"{where}|L{len(obj)}|".encode())
        for i, v in enumerate(obj):
            _feed(digest, f"{where}[{i}]", v)
    else:
        digest.update(f"{where}|{type(obj).__name__}|{obj!r}|".encode())


def save_checkpoint(path: str | Path, payload: dict[str, Any]) -> Path:
    """Save `payload` (plain containers and tensors only) atomically, with its content checksum."""
    payload = {"format": FORMAT, "version": VERSION, **{k: v for k, v in payload.items() if k not in _UNHASHED}}
    payload["checksum"] = content_checksum(payload)
    return atomic_write(path, lambda f: torch.save(payload, f))


def load_checkpoint(path: str | Path, allowed_targets: Iterable[str] = (), need_config: bool = False) -> dict[str, Any]:
    """Load a checkpoint safely (`weights_only=True`) and check it (module docstring) before it is used.

    Args:
        path: the file.
        allowed_targets: `_target_` names besides mpsim's own classes that its model config may use (those the
            user named in the config or on the command line).
        need_config: require `model.config` (to build a model from it; a `Trainer` used as a library may write
            checkpoints without one).

    Raises:
        CheckpointError: missing, empty, unreadable, not an mpsim checkpoint, incomplete, altered, non-finite
            weights, or a `_target_` outside the allowlist.
    """
    path = Path(path)
    why = not_a_regular_file(path)  # a named pipe is refused, never opened (reading it would block)
    if why is not None:
        raise CheckpointError(f"checkpoint {path} {why}.")
    if path.stat().st_size == 0:
        raise CheckpointError(
            f"checkpoint {path} is empty (0 bytes), e.g. an interrupted copy. Use another copy, the run's "
            "checkpoints/best.ckpt, or retrain."
        )
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - any unpickling failure means the same thing to the user
        lines = str(err).strip().splitlines()
        reason = f"{type(err).__name__}: {lines[0][:200]}" if lines else type(err).__name__
        raise CheckpointError(
            f"cannot read checkpoint {path}: {reason}. It may be truncated or not an mpsim checkpoint; retrain "
            "or point init= at another file."
        ) from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not an mpsim checkpoint (no '{FORMAT}' header).")
    version = payload.get("version", 0)
    if not isinstance(version, int):
        raise CheckpointError(f"{path}: 'version' must be an integer; got {version!r}. The file is damaged.")
    if version > VERSION:
        raise CheckpointError(
            f"{path} was written by a newer mpsim (checkpoint version {payload['version']} > {VERSION}); upgrade mpsim."
        )
    check_structure(payload, path, need_config)
    _verify_checksum(payload, path)
    _check_finite(payload, path)
    _read_history(payload, path)
    if "config" in payload["model"]:
        check_config_targets(payload["model"]["config"], f"{path}: model.config", allowed_targets)
    payload["path"] = str(path)
    return payload


def history_row(row: dict[str, Any], columns: Sequence[str]) -> str:
    """One metric row as JSON text for `history_text`: its values in `columns` order when it has exactly those
    keys (the trainer's rows do), otherwise the whole mapping."""
    if list(row) == list(columns):
        return json.dumps(list(row.values()))
    return json.dumps(row)


def history_text(columns: Sequence[str], rows: Sequence[str]) -> str:
    """A trainer state's `history_json`: the column names and every row's `history_row` text as one JSON object.

    `last.ckpt` is rewritten after every epoch and holds every row so far; as text dumped once per row, its
    checksum and save stay small over long runs (a list of dicts, hashed value by value, made a save take
    0.14 s at 4000 epochs and 0.23–0.26 s at 10000; as text 0.016–0.028 s)."""
    return '{"columns": ' + json.dumps(list(columns)) + ', "rows": [' + ",".join(rows) + "]}"


def _read_history(payload: dict[str, Any], path: str | Path) -> None:
    """Parse a trainer state's `history_json` into `history`, the list of metric rows callers read (older
    checkpoints store that list directly)."""
    trainer = payload.get("trainer")
    if not isinstance(trainer, dict) or "history_json" not in trainer:
        return
    text = trainer.pop("history_json")
    rows = None
    try:
        # already in memory (no size limit), but a deeply nested text would make json recurse: depth checked first
        parsed = parse_json(text, "history", "", sys.maxsize) if isinstance(text, str) else None
        if (
            isinstance(parsed, dict)
            and isinstance(parsed.get("columns"), list)
            and isinstance(parsed.get("rows"), list)
        ):
            columns = parsed["columns"]
            rows = [dict(zip(columns, r, strict=True)) if isinstance(r, list) else r for r in parsed["rows"]]
    except (ValueError, RecursionError, TypeError):
        rows = None
    if rows is None or not all(isinstance(r, dict) and all(isinstance(k, str) for k in r) for r in rows):
        raise CheckpointError(
            f"{path}: 'trainer.history_json' is not the table of metric rows a trainer writes; the file is "
            "damaged. Use another copy, or start the run again without resume."
        )
    trainer["history"] = rows


def check_structure(payload: dict[str, Any], path: str | Path, need_config: bool = True) -> None:
    """The keys and types every command reads from a checkpoint (one message naming the first that is wrong)."""
    fix = "The file is incomplete or was not written by mpsim; retrain to write a new one."
    for key in ("model", "normalisation", "system"):
        if key not in payload:
            raise CheckpointError(f"{path} lacks '{key}'; it is incomplete. Retrain to write a new one.")
        if not isinstance(payload[key], dict):
            raise CheckpointError(f"{path}: '{key}' must be a mapping; got {type(payload[key]).__name__}. {fix}")
    model = payload["model"]
    for key, kind in (("config", dict), ("state_dict", dict), ("state_dim", int)):
        if key not in model and key == "config" and not need_config:
            continue
        if key not in model:
            raise CheckpointError(f"{path} lacks 'model.{key}'. {fix}")
        if not isinstance(model[key], kind) or isinstance(model[key], bool):
            raise CheckpointError(
                f"{path}: 'model.{key}' must be {kind.__name__}; got {type(model[key]).__name__}. {fix}"
            )
    if model["state_dim"] < 1 or not isinstance(model.get("control_dim", 0), int) or model.get("control_dim", 0) < 0:
        raise CheckpointError(
            f"{path}: model.state_dim={model['state_dim']!r}, model.control_dim="
            f"{model.get('control_dim', 0)!r} are not sizes (>= 1, >= 0). {fix}"
        )
    if "config" in model and not isinstance(model["config"].get("_target_"), str):
        raise CheckpointError(f"{path}: 'model.config' has no '_target_' naming the model class. {fix}")
    bad = [k for k, v in model["state_dict"].items() if not isinstance(k, str) or not isinstance(v, torch.Tensor)]
    if bad:
        raise CheckpointError(f"{path}: 'model.state_dict' entry {bad[0]!r} is not a named tensor. {fix}")
    for key in ("mean", "std"):
        if not isinstance(payload["normalisation"].get(key), torch.Tensor):
            raise CheckpointError(f"{path} lacks the tensor 'normalisation.{key}'. {fix}")
    if "trainer" in payload and not isinstance(payload["trainer"], dict):
        raise CheckpointError(f"{path}: 'trainer' must be a mapping. {fix}")


def _verify_checksum(payload: dict[str, Any], path: str | Path) -> None:
    stored = payload.get("checksum")
    if stored is None:
        if payload.get("version", 0) >= 2:
            raise CheckpointError(
                f"{path} has no content checksum although its format requires one; it was "
                "altered after it was written. Use another copy or retrain."
            )
        log.warning(f"{path}: an older checkpoint without a content checksum; its integrity cannot be verified")
        return
    if stored != content_checksum(payload):
        raise CheckpointError(
            f"{path}: its content does not match the checksum stored in it: the file was altered or damaged "
            "after it was written (e.g. bytes overwritten inside a weight). Use another copy or retrain."
        )


def _check_finite(payload: dict[str, Any], path: str | Path) -> None:
    tensors = {
        **{f"model.state_dict[{k!r}]": v for k, v in payload["model"]["state_dict"].items()},
        "normalisation.mean": payload["normalisation"]["mean"],
        "normalisation.std": payload["normalisation"]["std"],
    }
    for name, t in tensors.items():
        if (t.is_floating_point() or t.is_complex()) and not bool(torch.isfinite(t).all()):
            n_bad = int((~torch.isfinite(t)).sum())
            raise CheckpointError(
                f"{path}: {name} holds NaN/inf ({n_bad} of {t.numel()} values): the model it stores is broken "
                "(saved after training diverged?). Use an earlier checkpoint, e.g. the run's checkpoints/best.ckpt, "
                "or retrain."
            )


# ---- _target_ allowlist --------------------------------------------------------------------------------
def config_targets(node: Any) -> set[str]:
    """Every `_target_` string in a nested config (dicts and lists)."""
    found: set[str] = set()
    if isinstance(node, dict):
        if isinstance(node.get("_target_"), str):
            found.add(node["_target_"])
        for value in node.values():
            found |= config_targets(value)
    elif isinstance(node, list | tuple):
        for value in node:
            found |= config_targets(value)
    return found


def is_mpsim_class(name: str) -> bool:
    """Whether `name` is the dotted name of a class defined in mpsim (imports only mpsim's own modules)."""
    if not _MPSIM_NAME.fullmatch(name):
        return False
    parts = name.split(".")
    for i in range(len(parts) - 1, 0, -1):
        try:
            obj: Any = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for attr in parts[i:]:
            obj = getattr(obj, attr, None)
        return inspect.isclass(obj) and getattr(obj, "__module__", "").split(".")[0] == "mpsim"
    return False


def check_config_targets(node: Any, where: str, allowed: Iterable[str] = ()) -> None:
    """Refuse a config read from a file whose `_target_`s leave the allowlist, or that holds interpolations.

    Raises:
        CheckpointError: names the first offending key.
    """
    allowed = set(allowed)

    def walk(obj: Any, at: str) -> None:
        if isinstance(obj, dict):
            if "_target_" in obj:
                target = obj["_target_"]
                if not isinstance(target, str) or (target not in allowed and not is_mpsim_class(target)):
                    raise CheckpointError(
                        f"{where}: {at}._target_={target!r} is not an mpsim class. A checkpoint is data: its config may "
                        "only name mpsim's own classes, or a class you name yourself on the command line or in the "
                        f"config (e.g. model._target_=<your class>). Refusing to build anything from it."
                    )
            for key, value in obj.items():
                walk(value, f"{at}.{key}")
        elif isinstance(obj, list | tuple):
            for i, value in enumerate(obj):
                walk(value, f"{at}[{i}]")
        elif isinstance(obj, str) and "${" in obj:
            raise CheckpointError(
                f"{where}: {at}={obj!r} holds an interpolation; a stored config must be plain values. "
                "Refusing to use it."
            )

    walk(node, "model")


# the data metadata a checkpoint keeps ("system"): first the keys that name the system and its shape, which mpsim
# reads back (`system` and `state_names` in messages, `n_nodes` for models tied to one graph size), then the rest
# within the budget
META_READ_BACK = (
    "system",
    "system_class",
    "state_names",
    "control_names",
    "n_nodes",
    "dt",
    "input_hold",
    "observed",
    "estimated",
)
META_BUDGET = 64_000  # bytes of JSON; best.ckpt, last.ckpt (rewritten every epoch) and the export each hold it


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
        "system": capped_meta(system_meta, "the checkpoints"),
        **(extra or {}),
    }


def capped_meta(meta: Mapping[str, Any], where: str, budget: int = META_BUDGET) -> dict[str, Any]:
    """`meta` reduced to plain values and at most `budget` bytes of JSON, so that a data file's large metadata is
    not copied into every checkpoint (or summary) written from it.

    The keys in `META_READ_BACK` are kept first, then the others from the smallest up while they fit; those
    left out are named in one warning (`where`: what is written). A key whose value cannot be serialised
    (nested too deeply) counts as too large.
    """
    plain: dict[str, Any] = {}
    sizes: dict[str, float] = {}
    for key, value in meta.items():
        try:
            plain[str(key)] = _plain_meta(value)
            sizes[str(key)] = len(json.dumps({str(key): plain[str(key)]}))
        except (RecursionError, ValueError, TypeError):
            plain[str(key)], sizes[str(key)] = None, float("inf")
    kept, used = set(), 0.0
    for key in sorted(plain, key=lambda k: (k not in META_READ_BACK, sizes[k])):
        if used + sizes[key] <= budget:
            kept.add(key)
            used += sizes[key]
    dropped = [k for k in plain if k not in kept]
    if dropped:
        named = ", ".join(
            f"{k} ({fmt_bytes(sizes[k]) if sizes[k] < float('inf') else 'nested too deeply'})" for k in dropped
        )
        log.warning(
            f"data metadata not copied into {where} (at most {fmt_bytes(budget)} of it is; the data file keeps it "
            f"all): {named}"
        )
    return {k: v for k, v in plain.items() if k in kept}


def _plain_meta(obj: Any) -> Any:
    """Metadata reduced to containers that `torch.load(weights_only=True)` accepts."""
    if isinstance(obj, dict):
        return {str(k): _plain_meta(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_plain_meta(v) for v in obj]
    if obj is None or isinstance(obj, bool | int | float | str):
        return obj
    return str(obj)
