"""The message for an override whose key names no key of the composed config: the closest keys, or how to add a
parameter that the target class takes but its config file does not list (Hydra's own advice, "To append to your
config use +key", is the wrong fix for a typo)."""

from __future__ import annotations

import difflib
import inspect
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from mpsim.config.targets import import_target
from mpsim.errors import ConfigError

#: top-level names users reach for, other tools' words for a key mpsim has
_SYNONYMS = {"ckpt": "init", "checkpoint": "init", "load": "init", "weights": "init", "epochs": "trainer.max_epochs"}


def unknown_key_message(key: str, others: list[str], compose_fn: Any, config_dir: str) -> str:
    """Message for `key=...` naming no key of the composed config: the closest keys, or how to add a parameter
    that the target class takes but its config file does not list."""
    parent, _, leaf = key.rpartition(".")
    if key.startswith("hydra.sweeper.params."):  # its keys hold dots: an override cannot reach them
        name = key.removeprefix("hydra.sweeper.params.")
        return (
            f"{key}: a search space is given on the key itself, '{name}=interval(low, high)', "
            f"'{name}=tag(log, interval(low, high))' or '{name}=choice(a, b)' (with hparams_search=...), or in a "
            "copy of conf/hparams_search/*.yaml."
        )
    try:
        base = compose_fn(others, hydra=True) if key.startswith("hydra.") else compose_fn(others)
    except Exception:  # noqa: BLE001
        return f"{key} is not a config key. Check its spelling (mpsim <command> --cfg job lists every key)."
    node = OmegaConf.select(base, parent) if parent else base
    if not isinstance(node, DictConfig):
        parts, here = key.split("."), base
        for depth, part in enumerate(parts[:-1]):
            if not isinstance(here, DictConfig) or part not in here:
                options = [str(k) for k in here.keys()] if isinstance(here, DictConfig) else []
                close = difflib.get_close_matches(part, options, n=3, cutoff=0.6)
                prefix = ".".join(parts[:depth])
                name = f"{prefix}.{part}" if prefix else part
                hint = (
                    f" Did you mean {' or '.join((prefix + '.' if prefix else '') + c for c in close)}?"
                    if close
                    else ""
                )
                return f"{key}: {name} is not a config section.{hint} (mpsim <command> --cfg job lists every key.)"
            here = here[part]
        return f"{key}: {parent} is not a config section (mpsim <command> --cfg job lists every key)."
    keys = [str(k) for k in node.keys()]
    where = f"{parent}." if parent else ""
    if not parent:  # a top-level name may also be a config group
        keys += [p.name for p in Path(config_dir).iterdir() if p.is_dir() and not p.name.startswith("_")]
    close = difflib.get_close_matches(leaf, keys, n=3, cutoff=0.6)
    if not parent and leaf in _SYNONYMS and _SYNONYMS[leaf].split(".")[0] in keys:
        close = [_SYNONYMS[leaf]]
    if close:
        return (
            f"{key} is not a config key. Did you mean {' or '.join(where + c for c in close)}? "
            f"Keys of {parent or 'the config'}: {', '.join(sorted(set(k for k in keys if not k.startswith('_'))))}."
        )
    target = node.get("_target_") if parent else None
    if isinstance(target, str):
        params: Mapping[str, inspect.Parameter]
        try:
            obj = import_target(target, parent)
            params = inspect.signature(obj.__init__ if inspect.isclass(obj) else obj).parameters
        except (ConfigError, TypeError, ValueError):
            params = {}
        if leaf in params:
            return (
                f"{key} is a parameter of {target} that {parent}'s config file does not list; add it with "
                f"+{key}=<value>."
            )
        close = difflib.get_close_matches(leaf, [p for p in params if p != "self"], n=3, cutoff=0.6)
        if close:
            return f"{key} is not a parameter of {target}. Did you mean {' or '.join(where + c for c in close)}?"
    listing = ", ".join(sorted({k for k in keys if not k.startswith("_")}))  # a group may also be a key
    return f"{key} is not a config key; {parent or 'the config'} has: {listing}."
