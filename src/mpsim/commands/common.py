"""What every command does with its config: runtime setup, systems, data, models and checkpoints.

This is the command layer: the only code that reads config objects. Everything below it takes plain
arguments.
"""

from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from hydra.core.hydra_config import HydraConfig
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf, open_dict

from mpsim.config import check_targets, validate_values
from mpsim.data.dataset import DatasetSpec, Splits, add_noise, fit_normalisation, simulate_splits, split_trajectories
from mpsim.data.io import check_representable, load_trajectories
from mpsim.data.trajectories import Trajectories
from mpsim.errors import CheckpointError, ConfigError, IncompatibleError, MpsimError
from mpsim.memory import check_fits, simulation_bytes, training_bytes
from mpsim.models.base import Model
from mpsim.solvers.odeint import ODESolver
from mpsim.systems.base import System
from mpsim.training.checkpoint import config_targets, load_checkpoint

log = logging.getLogger(__name__)

DTYPES = {"float32": torch.float32, "float64": torch.float64}


# ---- runtime -----------------------------------------------------------------------------------------------
@dataclass
class Runtime:
    device: torch.device
    dtype: torch.dtype
    start_dir: Path
    output_dir: Path
    overrides: list[str]


def hydra_overrides() -> list[str]:
    """The task overrides given on the command line (empty outside a Hydra run)."""
    if HydraConfig.initialized():
        return list(HydraConfig.get().overrides.task)
    return []


def is_multirun() -> bool:
    """Whether this process runs a job of a Hydra sweep (`-m`)."""
    return HydraConfig.initialized() and HydraConfig.get().mode.name == "MULTIRUN"


def locate(output_dir: str | Path | None = None) -> tuple[Path, Path]:
    """(directory the command was started from, this run's output directory), created if needed."""
    if HydraConfig.initialized():
        hc = HydraConfig.get()
        start_dir, output_dir = Path(hc.runtime.cwd), Path(output_dir or hc.runtime.output_dir)
    else:
        start_dir, output_dir = Path.cwd(), Path(output_dir or Path.cwd())
    output_dir.mkdir(parents=True, exist_ok=True)
    return start_dir, output_dir


def setup_runtime(cfg: DictConfig, output_dir: str | Path | None = None, overrides: list[str] | None = None) -> Runtime:
    """Check `_target_` nodes, seed, set threads and pick device/dtype; return where things go."""
    inline_specs(cfg)
    validate_values(cfg)
    check_targets(cfg)
    start_dir, output_dir = locate(output_dir)
    threads = cfg.get("threads")
    if threads is None and HydraConfig.initialized():
        launcher = HydraConfig.get().launcher
        if "joblib" in str(launcher.get("_target_", "")):
            n_jobs = int(launcher.get("n_jobs", -1) or -1)
            if n_jobs < 1:
                n_jobs = os.cpu_count() or 1
            threads = max(1, (os.cpu_count() or 1) // n_jobs)
    if threads:
        torch.set_num_threads(int(threads))
    torch.manual_seed(int(cfg.seed))
    if cfg.dtype not in DTYPES:
        raise ConfigError(f"dtype={cfg.dtype!r} is not supported; choose one of {sorted(DTYPES)}.")
    device = cfg.device
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if str(device).startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"device={device} but CUDA is not available on this machine; use device=cpu.")
    return Runtime(
        device=torch.device(device),
        dtype=DTYPES[cfg.dtype],
        start_dir=start_dir,
        output_dir=output_dir,
        overrides=hydra_overrides() if overrides is None else list(overrides),
    )


def inline_specs(cfg: DictConfig) -> None:
    """`system.spec=<file>` / `model.spec=<file>` (model=equations, system=equations): replace the file name by
    the file's content, so that checkpoints, dataset cache keys and summaries carry the equations themselves."""
    from mpsim.equations import load_spec_file

    start_dir = Path(HydraConfig.get().runtime.cwd) if HydraConfig.initialized() else Path.cwd()
    for key in ("system", "model"):
        node = cfg.get(key)
        if not isinstance(node, DictConfig) or not isinstance(node.get("spec"), str):
            continue
        path = resolve_path(node.spec, start_dir)
        content = load_spec_file(path)
        with open_dict(cfg):
            node.spec = content
            if key == "system" and "name" in node and node.name is None and not content.get("name"):
                node.name = re.sub(r"[^A-Za-z0-9_.-]", "_", path.stem)


def resolve_path(path: str | Path, start_dir: Path) -> Path:
    """An absolute path as given, else relative to the directory the command was started from."""
    path = Path(os.path.expanduser(str(path)))
    return path if path.is_absolute() else start_dir / path


def resolve_init(init: str, rt: Runtime, ckpt_dir: str) -> Path:
    """Find `init=`: an absolute path, a path from the start directory, then a name in `paths.ckpt_dir`."""
    ckpt_root = resolve_path(ckpt_dir, rt.start_dir)
    candidates = [resolve_path(init, rt.start_dir), ckpt_root / init]
    if not init.endswith(".ckpt"):
        candidates.append(ckpt_root / f"{init}.ckpt")
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    available = sorted(p.name for p in ckpt_root.glob("*.ckpt")) if ckpt_root.is_dir() else []
    listing = (
        f" Available in {ckpt_root}: {', '.join(available)}." if available else f" {ckpt_root} has no checkpoints."
    )
    raise CheckpointError(f"init={init}: no such checkpoint (looked for {', '.join(map(str, candidates))}).{listing}")


# ---- systems and data --------------------------------------------------------------------------------------
def build(node: DictConfig, where: str, **kwargs: Any) -> Any:
    """`hydra.utils.instantiate` with errors turned into one clear message naming the config key."""
    try:
        return instantiate(node, **kwargs)
    except InstantiationException as err:
        cause = err.__cause__
        if isinstance(cause, MpsimError):
            raise cause from None
        text = str(cause or err).strip().splitlines()[-1]
        raise ConfigError(f"cannot build {where} ({node.get('_target_')}): {text}") from None


def build_system(cfg: DictConfig) -> System:
    return build(cfg.system, "system")


def build_solver(cfg: DictConfig) -> ODESolver:
    return build(cfg.solver, "solver")


def system_spec(cfg: DictConfig) -> dict[str, Any]:
    """The system's config as plain data (part of the dataset cache key)."""
    return OmegaConf.to_container(cfg.system, resolve=True)  # type: ignore[return-value]


def load_splits(cfg: DictConfig, rt: Runtime, system: System | None) -> Splits:
    """Simulate the system's three splits (cached), or load `data.path` and split it by trajectory."""
    data = cfg.data
    if data.path:
        graph = None
        if data.graph == "system":
            if system is None:
                raise ConfigError("data.graph=system needs system=<name>.")
            graph = system.edge_index
        elif data.graph not in (None, "system"):
            raise ConfigError(f"data.graph={data.graph!r}: use null (graph from the file) or 'system'.")
        edges = resolve_path(data.edges, rt.start_dir) if data.edges else None
        loaded = load_trajectories(resolve_path(data.path, rt.start_dir), edges, graph, list(data.control_columns))
        log.info(
            f"loaded {len(loaded)} trajectories from {data.path}: T={loaded.n_times}, N={loaded.n_nodes}, "
            f"D={loaded.state_dim}"
        )
        check_representable(loaded, str(cfg.dtype), str(data.path))
        fit_horizons(cfg, rt, loaded.n_times - 1, f"data.path={data.path}")
        return split_trajectories(loaded, tuple(data.split), data.seed)
    if system is None:
        raise ConfigError("no data: pass system=<name> or data.path=<file>.")
    horizon = int(data.horizon or system.horizon)
    fit_horizons(cfg, rt, horizon, f"system={system.name} with {horizon} steps per trajectory")
    check_simulation_memory(cfg, system, [data.n_train, data.n_val, data.n_test], int(data.burn_in) + horizon + 1)
    cache_dir = resolve_path(cfg.paths.cache_dir, rt.start_dir) if data.cache else None
    spec = DatasetSpec(
        system=system_spec(cfg),
        n_train=data.n_train,
        n_val=data.n_val,
        n_test=data.n_test,
        seed=data.seed,
        dt=data.dt,
        horizon=data.horizon,
        burn_in=data.burn_in,
        rtol=data.gt_rtol,
        atol=data.gt_atol,
    )
    return simulate_splits(system, spec, cache_dir)


def fit_horizons(cfg: DictConfig, rt: Runtime, steps: int, source: str) -> None:
    """`eval.horizons` beyond the record (`steps` steps): refused when given explicitly, else the defaults that do
    not fit are dropped with a note."""
    horizons = [int(h) for h in cfg.eval.horizons]
    beyond = [h for h in horizons if h > steps]
    if not beyond:
        return
    if any(a.split("=", 1)[0].lstrip("+~") == "eval.horizons" for a in rt.overrides):
        raise ConfigError(
            f"eval.horizons={horizons}: {beyond} go beyond the record ({source}: steps 1..{steps}). "
            f"Give horizons <= {steps}, or a longer record (data.horizon=...)."
        )
    cfg.eval.horizons = [h for h in horizons if h <= steps] or [steps]
    log.warning(
        f"eval.horizons: default horizons {beyond} go beyond the record ({steps} steps); reporting "
        f"{list(cfg.eval.horizons)}"
    )


def check_simulation_memory(cfg: DictConfig, system: System, sizes: list[int], n_times: int) -> None:
    """Refuse, before simulating, data whose float64 arrays would not fit in memory (`memory_check=false` skips)."""
    need = simulation_bytes(sizes, n_times, system.n_nodes, system.state_dim)
    what = (
        f"simulating {' + '.join(map(str, sizes))} trajectories × {n_times} time points × {system.n_nodes:,} "
        f"nodes × {system.state_dim} states of system={system.name} (float64)"
    )
    check_fits(
        need,
        what,
        "cpu",
        bool(cfg.get("memory_check", True)),
        "fewer trajectories: data.n_train/n_val/n_test or n; a shorter data.horizon; a smaller system",
    )


def check_training_memory(
    cfg: DictConfig, rt: Runtime, model: Model, model_cfg: dict[str, Any], train: Trajectories
) -> None:
    """Refuse, before training, a step whose crude estimate (`mpsim.memory.training_bytes`) does not fit."""
    window = cfg.trainer.get("window")
    n_times = min(train.n_times, int(window) + 1) if window else train.n_times
    widths = [v for k, v in model_cfg.items() if "hidden" in str(k) and isinstance(v, int) and not isinstance(v, bool)]
    width = max([train.state_dim, *widths])
    batch = min(int(cfg.trainer.batch_size), len(train))
    itemsize = torch.finfo(rt.dtype).bits // 8
    values = train.x.numel() + (0 if train.u is None else train.u.numel())
    need = training_bytes(
        sum(p.numel() for p in model.parameters()), values, batch, n_times, train.n_nodes, width, itemsize
    )
    what = (
        f"training ({batch} trajectories × {n_times} time points × {train.n_nodes:,} nodes × {width} features "
        f"per step, {rt.dtype})"
    )
    check_fits(
        need,
        what,
        str(rt.device),
        bool(cfg.get("memory_check", True)),
        "trainer.batch_size; trainer.window; a smaller model or system",
    )


def noisy_train(splits: Splits, std: torch.Tensor, scale: float, seed: int) -> Splits:
    """Training split with measurement noise (`data.noise_std` × feature std); val/test stay clean."""
    return Splits(train=add_noise(splits.train, std, scale, seed), val=splits.val, test=splits.test)


# ---- models and checkpoints --------------------------------------------------------------------------------
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
    current = OmegaConf.to_container(cfg.model, resolve=True)
    if ckpt is None:
        return current  # type: ignore[return-value]
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
        raise IncompatibleError(
            f"{ckpt['path']} was trained on {meta.get('system')} ({ck_d} states {meta.get('state_names')}, "
            f"{ck_c} controls per node) but this data has {state_dim} states {state_names} and {control_dim} "
            "controls per node. Use a checkpoint of a system with the same node state, or drop init=."
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
    cfg: DictConfig, rt: Runtime, system: System | None, ckpt: dict[str, Any] | None, refit: bool
) -> tuple[Model, dict[str, Any], Splits]:
    """Model and splits, checked in the order that writes nothing before a bad input is found: the model
    (and checkpoint) is checked against the system before any data is simulated into the cache."""
    splits = load_splits(cfg, rt, system) if cfg.data.path else None
    model, model_cfg = build_model_for(cfg, rt, Shape.of(splits.train if splits else system), ckpt)
    if splits is None:
        splits = load_splits(cfg, rt, system)
    if ckpt is None or refit:
        model.set_normalisation(*fit_normalisation(splits.train))
    return model, model_cfg, splits


def load_init(cfg: DictConfig, rt: Runtime) -> dict[str, Any] | None:
    if not cfg.init:
        return None
    path = resolve_init(str(cfg.init), rt, cfg.paths.ckpt_dir)
    # a checkpoint may name mpsim's classes, and those the user's own config names (e.g. model._target_=...)
    allowed = config_targets(OmegaConf.to_container(cfg.model, resolve=True)) if cfg.get("model") is not None else set()
    ckpt = load_checkpoint(path, allowed, need_config=True)
    log.info(f"init: {path}")
    return ckpt
