"""Checks of the `_target_` nodes (system, model, solver, ...): they differ per target, so each is checked against
its target's own signature. Unknown keys get a did-you-mean, values are checked against the parameter annotations;
a user who points a group at their own class gets the same checks for free."""

from __future__ import annotations

import difflib
import importlib
import inspect
import types
import typing
from typing import Any, cast

from omegaconf import DictConfig, OmegaConf

from mpsim.errors import ConfigError


def plain_dict(node: DictConfig) -> dict[str, Any]:
    """A config section as plain, resolved Python data (`OmegaConf.to_container` is typed for any node)."""
    out = OmegaConf.to_container(node, resolve=True)
    assert isinstance(out, dict)  # a DictConfig converts to a dict
    return cast(dict[str, Any], out)  # OmegaConf types the keys as any primitive; mpsim's sections use names


def import_target(path: str, where: str) -> Any:
    """The object a `_target_` names (`where` is the config key, for the message)."""
    module, _, name = path.rpartition(".")
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError, ValueError):
        raise ConfigError(
            f"{where}._target_: cannot import {path!r}. Check the spelling or install its package."
        ) from None


def _type_ok(value: Any, annotation: Any) -> bool:
    """Whether `value` (a plain config value) fits `annotation` (conservative: unknown annotations pass)."""
    if annotation is inspect.Parameter.empty or annotation is Any:
        return True
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        return any(_type_ok(value, a) for a in typing.get_args(annotation))
    if annotation is type(None):
        return value is None
    if annotation is bool:
        return isinstance(value, bool)
    if annotation is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if annotation is float:
        return isinstance(value, int | float) and not isinstance(value, bool)
    if annotation is str:
        return isinstance(value, str)
    if origin in (list, tuple, typing.Sequence) or annotation in (list, tuple):
        return isinstance(value, list | tuple)
    if origin is dict or annotation is dict:
        return isinstance(value, dict)
    return True


def _describe(annotation: Any) -> str:
    return getattr(annotation, "__name__", None) or str(annotation).replace("typing.", "")


def check_target_node(node: Any, where: str) -> None:
    """Check one `_target_` node's keys and values against its target's signature.

    Raises:
        ConfigError: unknown key (with suggestions) or a value of the wrong type.
    """
    if not isinstance(node, dict) or "_target_" not in node:
        return
    target = import_target(node["_target_"], where)
    func = target.__init__ if inspect.isclass(target) else target
    try:
        sig = inspect.signature(func)
        hints = typing.get_type_hints(func)
    except (TypeError, ValueError, NameError):
        return
    params = {k: p for k, p in sig.parameters.items() if k != "self"}
    if any(p.kind is p.VAR_KEYWORD for p in params.values()):
        return
    for key, value in node.items():
        if key.startswith("_"):
            continue
        if key not in params:
            close = difflib.get_close_matches(key, list(params), n=3)
            hint = f" Did you mean {' or '.join(close)}?" if close else ""
            raise ConfigError(
                f"{where}.{key} is not a parameter of {node['_target_']}.{hint} "
                f"Valid keys: {', '.join(k for k in params if k not in ('effects',))}."
            )
        annotation = hints.get(key, params[key].annotation)
        if not _type_ok(value, annotation):
            raise ConfigError(
                f"{where}.{key}={value!r} has the wrong type: {node['_target_']} expects {_describe(annotation)}."
            )


def check_targets(cfg: DictConfig, keys: tuple[str, ...] = ("system", "model", "solver")) -> None:
    """Check every listed `_target_` node of a composed config (see `check_target_node`)."""
    for key in keys:
        if key in cfg and cfg[key] is not None:
            check_target_node(OmegaConf.to_container(cfg[key], resolve=True), key)
