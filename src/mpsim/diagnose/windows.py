"""Window rollouts: the model rolled out over consecutive windows of the records, and its residuals on them.

Windows start every `length` steps at the same step index in every trajectory (one batched rollout per start,
so absolute time stays right for time-dependent terms — a drive, the data's inputs; the loop is over the few
window starts in time, every trajectory and node of a window at once); the last window may be shorter.
Residuals are on the measured states only (`Trajectories.observed_index`): a latent state is not a target.
"""

from __future__ import annotations

import torch

from mpsim.data.trajectories import Trajectories
from mpsim.metrics import select_features
from mpsim.models.base import Model


def window_starts(n_times: int, length: int) -> list[int]:
    """The first step of every window of `length` steps over a record of `n_times` samples."""
    return list(range(0, n_times - 1, max(length, 1)))


def window_predictions(
    model: Model,
    data: Trajectories,
    length: int,
    starts: torch.Tensor | None = None,  # [B, K, N, D] each window's initial state (None: the data's)
) -> list[tuple[int, torch.Tensor]]:
    """[(start, [B, L+1, N, D] rollout over the next ≤ length steps)], gradients kept. Each window starts from
    the data's state at its first step, or from `starts` (K = the number of windows; latent states fitted by
    `mpsim.diagnose.latent`)."""
    device, dtype = model.state_mean.device, model.state_mean.dtype
    x = data.x.to(device=device, dtype=dtype)
    t = data.t.to(device=device, dtype=dtype)
    first = window_starts(data.n_times, length)
    x0 = x[:, first] if starts is None else starts.to(device=device, dtype=dtype)  # [B, K, N, D]
    out = []
    for k, s in enumerate(first):  # sequential in time only; each rollout batches every trajectory
        end = min(s + length, data.n_times - 1)
        out.append((s, model.rollout(x0[:, k], t[s : end + 1], data.inputs(s, end + 1).to(device, dtype))))
    return out


def window_residuals(
    model: Model,
    data: Trajectories,
    length: int,
    starts: torch.Tensor | None = None,  # [B, K, N, D] each window's initial state (None: the data's)
) -> tuple[torch.Tensor, torch.Tensor]:
    """([B, K, L, N, D_obs] normalised residuals (prediction − data) of every window's predicted steps on the
    measured states, zero past the end of a shorter last window; [K, L] which steps exist), L = the longest
    window's steps; gradients kept."""
    observed = data.observed_index
    std = model.state_std.detach()
    preds = window_predictions(model, data, length, starts)
    steps = max(p.shape[1] for _, p in preds) - 1
    parts, mask = [], torch.zeros(len(preds), steps, dtype=torch.bool)
    for k, (s, pred) in enumerate(preds):  # the few window starts (the rollouts above are per start already)
        n = pred.shape[1] - 1
        true = data.x[:, s + 1 : s + 1 + n].to(pred)
        res = select_features((pred[:, 1:] - true) / std.to(pred), observed)
        parts.append(torch.nn.functional.pad(res, (0, 0, 0, 0, 0, steps - n)))
        mask[k, :n] = True
    return torch.stack(parts, dim=1), mask
