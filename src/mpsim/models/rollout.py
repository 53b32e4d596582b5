"""`rollout`: a model's free-running prediction of whole trajectories, and its normalised error.

Free functions on the models floor (learning_to_simulate's `rollout(simulator, features, num_steps)`): the
trainer, the evaluation, `mpsim simulate init=` and the residual loop all predict through `rollout`.
"""

from __future__ import annotations

import math

import torch

from mpsim.data.trajectories import Trajectories
from mpsim.errors import DivergenceError
from mpsim.metrics import rollout_metrics
from mpsim.models.base import Model


def rollout(
    model: Model,
    data: Trajectories,
    *,
    batch_size: int = 512,
    aux: bool = False,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Roll `model` out from every trajectory's first state (its first `context_steps` states), in batches, without
    gradients, on the model's device and dtype; the predictions come back on the CPU.

    A batch whose solve fails (step-size underflow) is filled with NaN and reported as diverged by the
    metrics instead of aborting the evaluation.

    Args:
        model: the model (its normalisation buffers set, as after training or `load_checkpoint`).
        data: the trajectories to predict: their times, graph, controls and node features are the inputs,
            their first state(s) the initial condition.
        batch_size: trajectories per batch.
        aux: also return the model's auxiliary signals (`Model.rollout_aux`).

    Returns:
        ([B, T, N, D] predictions in raw units, auxiliary signals such as MP-NODE messages [B, T, N, M]; empty
        without `aux`).

    Examples:
        >>> import torch
        >>> from mpsim import rollout, simulate
        >>> from mpsim.models import MPNODE
        >>> from mpsim.systems import CoupledPendulums
        >>> data = simulate(CoupledPendulums(), 2, horizon=5)
        >>> _ = torch.manual_seed(0)
        >>> pred, _ = rollout(MPNODE(data.state_dim), data)
        >>> tuple(pred.shape) == tuple(data.x.shape)
        True
    """
    preds, auxes = [], []
    device = model.state_mean.device
    t = data.t.to(device)
    with torch.no_grad():
        for start in range(0, len(data), batch_size):
            part = data.subset(slice(start, start + batch_size)).to(device, model.state_mean.dtype)
            try:
                x0, tt, inputs = model.initial(part.x), t.to(part.x.dtype), part.inputs()
                p, a = model.rollout_aux(x0, tt, inputs) if aux else (model.rollout(x0, tt, inputs), {})
            except DivergenceError:
                p, a = torch.full_like(part.x, math.nan), {}
            preds.append(p.cpu())
            auxes.append({k: v.cpu() for k, v in a.items()})
    merged = {k: torch.cat([a[k] for a in auxes]) for k in auxes[0]} if auxes and all(auxes) else {}
    return torch.cat(preds), merged


def rollout_error(
    model: Model,
    data: Trajectories,
    *,
    batch_size: int = 512,
    pred: torch.Tensor | None = None,  # [B, T, N, D] predictions of `data` (None: `rollout` them)
) -> float:
    """Normalised rollout RMSE of `model` on `data` over the steps after its context (1..T−1 for one initial
    state) and the measured states (`Trajectories.observed_index`: a latent state is no target), NaN if every
    trajectory diverged; `pred` gives predictions made elsewhere (gathered from several processes) instead of
    rolling out here."""
    if pred is None:
        pred, _ = rollout(model, data, batch_size=batch_size)
    std = model.state_std.cpu().to(pred.dtype)
    periods = data.meta.get("periods")
    metrics = rollout_metrics(
        pred, data.x.to(pred.dtype), std, data.t, periods=periods, first=model.context_steps,
        features=data.observed_index,
    )  # fmt: skip
    return metrics["rmse"]
