"""A command's data: the system's simulated splits (cached) or a loaded file split by trajectory, the evaluation
horizons that fit the record, training noise, and the memory checks that refuse a size before any work starts.
"""

from __future__ import annotations

import logging
from typing import Any

import torch
from omegaconf import DictConfig

from mpsim.commands.runtime import Runtime, resolve_path
from mpsim.config import plain_dict
from mpsim.data.dataset import SPLITS, DatasetSpec, Splits, add_noise, simulate_splits, split_trajectories
from mpsim.data.io import check_representable, load_trajectories
from mpsim.data.trajectories import Trajectories
from mpsim.errors import ConfigError
from mpsim.memory import check_fits, model_bytes, simulation_bytes, training_bytes
from mpsim.models.base import Model
from mpsim.systems.base import System

log = logging.getLogger(__name__)


def system_spec(cfg: DictConfig) -> dict[str, Any]:
    """The system's config as plain data (part of the dataset cache key)."""
    return plain_dict(cfg.system)


def load_splits(cfg: DictConfig, rt: Runtime, system: System | None, need: tuple[str, ...] = SPLITS) -> Splits:
    """Simulate the system's three splits (cached), or load `data.path` and split it by trajectory (the splits in
    `need` get a share > 0; see `split_trajectories`)."""
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
        return split_trajectories(loaded, tuple(data.split), data.seed, need)
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


def check_model_memory(
    cfg: DictConfig, rt: Runtime, model: Model, model_cfg: dict[str, Any], training: bool, source: str | None = None
) -> None:
    """Refuse, before it is allocated, a model whose weights (for `training` with gradients and Adam's moments)
    do not fit. `model`: the planned model, on the meta device (sizes, no storage); `source`: the checkpoint its
    config came from."""
    params = list(model.parameters())
    param_bytes = sum(p.numel() * p.element_size() for p in params)
    buffer_bytes = sum(b.numel() * b.element_size() for b in model.buffers())
    n_params = sum(p.numel() for p in params)
    sizes = ", ".join(
        f"{k}={v}" for k, v in model_cfg.items() if isinstance(v, int) and not isinstance(v, bool) and v > 1
    )
    what = (
        f"model {model_cfg.get('_target_')} ({sizes or 'as configured'}{'; from ' + source if source else ''}): "
        f"{n_params:,} weights{' with their gradients and optimiser state' if training else ''} ({rt.dtype})"
    )
    check_fits(
        model_bytes(param_bytes, buffer_bytes, training),
        what,
        str(rt.device),
        bool(cfg.get("memory_check", True)),
        "another checkpoint, smaller model.* sizes on the command line, or a device with more memory"
        if source
        else "smaller model.* sizes, e.g. model.hidden",
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


def noisy_train(
    splits: Splits,
    std: torch.Tensor,  # [D] per-feature std of the training states
    scale: float,
    seed: int,
    dtype: torch.dtype = torch.float32,  # what the run computes in
) -> Splits:
    """Training split with measurement noise (`data.noise_std` × feature std); val/test stay clean. A noise level
    whose states `dtype` cannot hold is a ConfigError (they would become inf)."""
    train = add_noise(splits.train, std, scale, seed)
    if float(train.x.abs().max()) > torch.finfo(dtype).max:
        raise ConfigError(
            f"data.noise_std={scale:g} (times each feature's std) makes training states beyond the largest "
            f"{str(dtype).split('.')[-1]} ({torch.finfo(dtype).max:.2g}); give a noise level of the order of 0.01–1."
        )
    return Splits(train=train, val=splits.val, test=splits.test)
