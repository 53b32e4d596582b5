"""Objects from config: `hydra.utils.instantiate` with one clear message per failure, the system and the solver,
and the model — from scratch or with a checkpoint's config and weights, checked against the data's shape, its
sizes planned on the meta device and checked (weights vs config, memory) before anything is allocated.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import torch
from hydra.errors import InstantiationException
from hydra.utils import instantiate

from mpsim.commands.guards import check_model_memory
from mpsim.commands.init_ckpt import check_checkpoint_system, check_weights_fit, load_weights
from mpsim.commands.runtime import Runtime
from mpsim.data.trajectories import Trajectories
from mpsim.errors import ConfigError, IncompatibleError, MpsimError, ResourceError
from mpsim.models.base import Model
from mpsim.solvers.odeint import ODESolver
from mpsim.systems.base import System

log = logging.getLogger(__name__)


def build(node: Mapping[str, Any], where: str, **kwargs: Any) -> Any:
    """`hydra.utils.instantiate` of a `_target_` node (plain data) with errors turned into one clear message
    naming the config key `where`."""
    try:
        return instantiate(node, **kwargs)
    except InstantiationException as err:
        cause = err.__cause__
        if isinstance(cause, MpsimError):
            raise cause from None
        if isinstance(cause, MemoryError):
            raise ResourceError(
                f"building {where} ({node.get('_target_')}) ran out of memory; make it smaller (fewer nodes, a "
                "sparser graph)."
            ) from None
        lines = str(cause or err).strip().splitlines()
        text = lines[-1] if lines else type(cause or err).__name__
        raise ConfigError(f"cannot build {where} ({node.get('_target_')}): {text}") from None


def explicit_model_keys(overrides: list[str]) -> tuple[set[str], bool]:
    """(model.* keys given on the command line, whether the model group itself was chosen)."""
    keys, group = set(), False
    for item in overrides:
        key = item.split("=", 1)[0].lstrip("+~")
        if key == "model":
            group = True
        elif key.startswith("model."):
            keys.add(key[len("model.") :].split(".")[0])
    return keys, group


def model_config(current: dict[str, Any], ckpt: dict[str, Any] | None, overrides: list[str]) -> dict[str, Any]:
    """The model config to build: the checkpoint's, with the command line's `model.*` overrides (`current`: the
    command's model config) on top. Without a checkpoint it is simply `current`.
    """
    if ckpt is None:
        return current
    saved = dict(ckpt["model"]["config"])
    keys, group_chosen = explicit_model_keys(overrides)
    if group_chosen and current.get("_target_") != saved.get("_target_"):
        raise IncompatibleError(
            f"{ckpt['path']} holds a {saved.get('_target_')} model but model= asks for {current.get('_target_')}. "
            "Drop the model= override or use a checkpoint of that model."
        )
    for key in keys:
        if key in current:
            saved[key] = current[key]
    return saved


def build_model(
    model_cfg: dict[str, Any],
    state_dim: int,
    control_dim: int,
    solver: ODESolver,
    rt: Runtime,
) -> Model:
    model = build(model_cfg, "model", state_dim=state_dim, control_dim=control_dim, solver=solver)
    if not isinstance(model, Model):
        raise ConfigError(f"model._target_={model_cfg.get('_target_')} does not build an mpsim Model.")
    return model.to(device=rt.device, dtype=rt.dtype)


@dataclass(frozen=True)
class Shape:
    """What a model must fit: per-node state and control sizes, node count, state and control names."""

    state_dim: int
    control_dim: int
    n_nodes: int
    state_names: list[str]
    control_names: list[str] = field(default_factory=list)

    @staticmethod
    def of(source: System | Trajectories) -> Shape:
        names = list(
            (source.meta.get("control_names") if isinstance(source, Trajectories) else source.control_names) or []
        )
        return Shape(source.state_dim, source.control_dim, source.n_nodes, list(source.state_names), names)


def build_model_for(
    model_cfg: dict[str, Any],
    solver: ODESolver,
    rt: Runtime,
    shape: Shape,
    ckpt: dict[str, Any] | None,
    training: bool = False,
) -> Model:
    """Build the model for data of `shape`, from scratch or with `ckpt`'s weights, checking that they fit.

    Its sizes are checked before anything is allocated (`planned_model`): a checkpoint's weights must have the
    shapes its config builds, and the weights (with, when `training`, their gradients and Adam's moments) must
    fit in memory."""
    if ckpt is not None:
        check_checkpoint_system(ckpt, shape.state_dim, shape.control_dim, shape.state_names)
    trained_nodes = None if ckpt is None else ckpt["system"].get("n_nodes")
    plan = planned_model(model_cfg, shape, solver, rt, trained_nodes)
    if plan is not None:
        if ckpt is not None:
            check_weights_fit(plan.state_dict(), ckpt, model_cfg)
        check_model_memory(rt, plan, model_cfg, training, None if ckpt is None else ckpt["path"])
    model = _assemble(model_cfg, shape, solver, rt, trained_nodes)
    if ckpt is not None:
        load_weights(model, ckpt, model_cfg)
    return model


def _assemble(
    model_cfg: dict[str, Any], shape: Shape, solver: ODESolver, rt: Runtime, trained_nodes: int | None
) -> Model:
    """The model of `model_cfg`, its effects bound to the data's state names, checked to run on data of `shape`."""
    model = build_model(model_cfg, shape.state_dim, shape.control_dim, solver, rt)
    model.bind_effects(shape.state_names)
    if shape.control_names:
        model.bind_inputs(shape.control_names)
    model.check_compatible(shape.state_dim, shape.control_dim, shape.n_nodes, trained_nodes)
    return model


def planned_model(
    model_cfg: dict[str, Any], shape: Shape, solver: ODESolver, rt: Runtime, trained_nodes: int | None
) -> Model | None:
    """The model `model_cfg` builds, on PyTorch's meta device: every tensor has its shape and dtype but no
    storage, so sizes read from a config or a checkpoint are checked before they cost memory.

    None when the model cannot be built that way: its constructor computes with tensor values (`model=physics`
    builds its system, whose coupling and graph are drawn; `model=equations` tests its spec's values). Such a
    model is checked once it is built (its weights are values written in its config); any error raised here is
    raised again, with its message, by the real build.
    """
    try:
        with torch.device("meta"):
            return _assemble(model_cfg, shape, solver, replace(rt, device=torch.device("meta")), trained_nodes)
    except Exception as err:  # noqa: BLE001 - the real build reports a genuine error the same way
        log.debug(f"model sizes not planned on the meta device ({type(err).__name__}: {err}); checked once built")
        return None
