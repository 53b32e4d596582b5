"""Checks a command makes before any work starts, on plain values: the evaluation horizons that fit the record,
the memory a simulation, a model's weights and a training step would take (refused before they are allocated),
and the training split's measurement noise (`data.noise_std`).
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import Any

import torch

from mpsim.commands.runtime import Runtime
from mpsim.data.dataset import Splits, add_noise
from mpsim.data.trajectories import Trajectories
from mpsim.errors import ConfigError
from mpsim.memory import check_fits, model_bytes, simulation_bytes, training_bytes
from mpsim.models.base import Model
from mpsim.systems.base import System

log = logging.getLogger(__name__)


def fit_horizons(horizons: list[int], explicit: bool, steps: int, source: str) -> list[int]:
    """`eval.horizons` that fit a record of `steps` steps: those beyond it are refused when given `explicit`ly
    (on the command line), else dropped with a note."""
    beyond = [h for h in horizons if h > steps]
    if not beyond:
        return list(horizons)
    if explicit:
        raise ConfigError(
            f"eval.horizons={horizons}: {beyond} go beyond the record ({source}: steps 1..{steps}). "
            f"Give horizons <= {steps}, or a longer record (data.horizon=...)."
        )
    kept = [h for h in horizons if h <= steps] or [steps]
    log.warning(f"eval.horizons: default horizons {beyond} go beyond the record ({steps} steps); reporting {kept}")
    return kept


def check_simulation_memory(system: System, sizes: list[int], n_times: int, enabled: bool = True) -> None:
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
        enabled,
        "fewer trajectories: data.n_train/n_val/n_test or n; a shorter data.horizon; a smaller system",
    )


def check_model_memory(
    rt: Runtime, model: Model, model_cfg: dict[str, Any], training: bool, source: str | None = None
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
        rt.memory_check,
        "another checkpoint, smaller model.* sizes on the command line, or a device with more memory"
        if source
        else "smaller model.* sizes, e.g. model.hidden",
    )


def check_training_memory(
    rt: Runtime,
    model: Model,
    model_cfg: dict[str, Any],
    train: Trajectories,
    batch_size: int,
    window: int | None,
) -> None:
    """Refuse, before training, a step whose crude estimate (`mpsim.memory.training_bytes`) does not fit."""
    n_times = min(train.n_times, int(window) + 1) if window else train.n_times
    widths = [v for k, v in model_cfg.items() if "hidden" in str(k) and isinstance(v, int) and not isinstance(v, bool)]
    width = max([train.state_dim, *widths])
    batch = min(int(batch_size), len(train))
    itemsize = torch.finfo(rt.dtype).bits // 8
    values = train.x.numel() + (0 if train.u is None else train.u.numel())
    need = training_bytes(
        sum(p.numel() for p in model.parameters()), values, batch, n_times, train.n_nodes, width, itemsize
    )
    what = (
        f"training ({batch} trajectories × {n_times} time points × {train.n_nodes:,} nodes × {width} features "
        f"per step, {rt.dtype})"
    )
    fix = "trainer.batch_size; trainer.window; a smaller model or system"
    if "segments" in train.meta:  # recordings: shorter segments or fewer samples shrink every step
        fix = "data.segment=<shorter>; data.stride=<k> keeps every k-th sample; " + fix
    check_fits(need, what, str(rt.device), rt.memory_check, fix)


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
    return replace(splits, train=train)
