"""Objects from config: `hydra.utils.instantiate` with one clear message per failure, the system and the solver,
and the model — from scratch or with a checkpoint's config and weights, checked against the data's shape.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from mpsim.commands.checkpoints import check_checkpoint_system, load_weights
from mpsim.commands.runtime import Runtime
from mpsim.commands.splits import load_splits
from mpsim.config import plain_dict
from mpsim.data.dataset import SPLITS, Splits, fit_normalisation
from mpsim.data.trajectories import Trajectories
from mpsim.errors import ConfigError, IncompatibleError, MpsimError, ResourceError
from mpsim.models.base import Model
from mpsim.solvers.odeint import ODESolver
from mpsim.systems.base import System


def build(node: DictConfig, where: str, **kwargs: Any) -> Any:
    """`hydra.utils.instantiate` with errors turned into one clear message naming the config key."""
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


def build_system(cfg: DictConfig) -> System:
    return build(cfg.system, "system")


def build_solver(cfg: DictConfig) -> ODESolver:
    return build(cfg.solver, "solver")


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


def model_config(cfg: DictConfig, ckpt: dict[str, Any] | None, overrides: list[str]) -> dict[str, Any]:
    """The model config to build: the checkpoint's, with the command line's `model.*` overrides on top.

    Without a checkpoint it is simply `cfg.model`.
    """
    current = plain_dict(cfg.model)
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
    node = OmegaConf.create(model_cfg)
    model = build(node, "model", state_dim=state_dim, control_dim=control_dim, solver=solver)
    if not isinstance(model, Model):
        raise ConfigError(f"model._target_={model_cfg.get('_target_')} does not build an mpsim Model.")
    return model.to(device=rt.device, dtype=rt.dtype)


@dataclass(frozen=True)
class Shape:
    """What a model must fit: per-node state and control sizes, node count, state names."""

    state_dim: int
    control_dim: int
    n_nodes: int
    state_names: list[str]

    @staticmethod
    def of(source: System | Trajectories) -> Shape:
        return Shape(source.state_dim, source.control_dim, source.n_nodes, list(source.state_names))


def build_model_for(
    cfg: DictConfig, rt: Runtime, shape: Shape, ckpt: dict[str, Any] | None
) -> tuple[Model, dict[str, Any]]:
    """Build the model for data of `shape`, from scratch or with `ckpt`'s weights, checking that they fit."""
    if ckpt is not None:
        check_checkpoint_system(ckpt, shape.state_dim, shape.control_dim, shape.state_names)
    model_cfg = model_config(cfg, ckpt, rt.overrides)
    model = build_model(model_cfg, shape.state_dim, shape.control_dim, build_solver(cfg), rt)
    model.bind_effects(shape.state_names)
    trained_nodes = None if ckpt is None else ckpt["system"].get("n_nodes")
    model.check_compatible(shape.state_dim, shape.control_dim, shape.n_nodes, trained_nodes)
    if ckpt is not None:
        load_weights(model, ckpt, model_cfg)
    return model, model_cfg


def model_and_data(
    cfg: DictConfig,
    rt: Runtime,
    system: System | None,
    ckpt: dict[str, Any] | None,
    refit: bool,
    need: tuple[str, ...] = SPLITS,
) -> tuple[Model, dict[str, Any], Splits]:
    """Model and splits, checked in the order that writes nothing before a bad input is found: the model
    (and checkpoint) is checked against the system before any data is simulated into the cache. `need`: the
    splits the command uses (a file's other splits may be given no share)."""
    splits = load_splits(cfg, rt, system, need) if cfg.data.path else None
    source = (splits.train if len(splits.train) else splits.test) if splits else system
    if source is None:
        raise ConfigError("no data: pass system=<name> or data.path=<file>.")
    model, model_cfg = build_model_for(cfg, rt, Shape.of(source), ckpt)
    if splits is None:
        splits = load_splits(cfg, rt, system)
    if ckpt is None or refit:
        model.set_normalisation(*fit_normalisation(splits.train))
    return model, model_cfg, splits
