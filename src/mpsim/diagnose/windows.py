"""Window rollouts: the model rolled out over consecutive windows of the records, and its residuals on them.

Windows start every `length` steps at the same step index in every trajectory (one batched rollout per start,
so absolute time stays right for time-dependent terms — a drive, the data's inputs; the loop is over the few
window starts in time, every trajectory and node of a window at once); the last window may be shorter.
Residuals are on the measured states only (`Trajectories.observed_index`): a latent state is not a target.
A model with a delayed effect reads the record before each window's start as its history (`Inputs.past`: the
samples back to its longest delay, the record's first state held before the record began).
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch

from mpsim.data.trajectories import Inputs, Trajectories
from mpsim.effects import max_delay
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
    `mpsim.diagnose.latent`).

    A time-invariant model (`Model.time_invariant`) on a uniform grid rolls every full-length window out in
    one batch of K·B records on the first window's times (25 windows of 40 steps: 40 solver steps, not 1000);
    otherwise the windows run one after another, each on its own absolute times."""
    device, dtype = model.state_mean.device, model.state_mean.dtype
    x = data.x.to(device=device, dtype=dtype)
    t = data.t.to(device=device, dtype=dtype)
    first = window_starts(data.n_times, length)
    x0 = x[:, first] if starts is None else starts.to(device=device, dtype=dtype)  # [B, K, N, D]
    full = [k for k, s in enumerate(first) if s + length <= data.n_times - 1]
    out: dict[int, tuple[int, torch.Tensor]] = {}
    if len(full) > 1 and model.time_invariant and _uniform(data.t, [first[k] for k in full], length):
        out.update(zip(full, _batched(model, data, x0, t, [first[k] for k in full], full, length), strict=True))
    for k, s in enumerate(first):  # sequential in time only; each rollout batches every trajectory
        if k not in out:
            end = min(s + length, data.n_times - 1)
            inputs = data.inputs(s, end + 1).to(device, dtype)
            before = past_samples(model, data, [s])
            inputs = inputs if before is None else replace(inputs, past=x[:, before[0]])
            out[k] = (s, model.rollout(x0[:, k], t[s : end + 1], inputs))
    return [out[k] for k in range(len(first))]


def past_samples(model: Model, data: Trajectories, first: list[int]) -> torch.Tensor | None:
    """[K, P] the indices of the P samples before each window start in `first` that the model's longest delay
    reaches back to (clamped at the record's first sample: the history before it is held), or None for a model
    without delayed effects."""
    reach = max_delay(model.effects)
    if reach <= 0 or data.n_times < 2:
        return None
    # one more sample: the interpolation's left knot; never more than the record (before it the history is held)
    p = min(math.ceil(reach / float(data.t[1] - data.t[0]) - 1e-9) + 1, data.n_times)
    return (torch.tensor(first)[:, None] - p + torch.arange(p)).clamp(min=0)


def _uniform(t: torch.Tensor, first: list[int], length: int) -> bool:  # t: [T]
    """Whether every window starting at `first` has the first window's time steps (a uniform grid, to 1e-6 of a
    step)."""
    t = t.double()
    local = torch.stack([t[s : s + length + 1] - t[s] for s in first])  # [K, L+1] the few window starts
    ref = local[0]
    return bool((local - ref).abs().max() <= 1e-6 * (ref[-1] / length).abs().clamp(min=1e-300))


def _batched(
    model: Model,
    data: Trajectories,
    x0: torch.Tensor,  # [B, K, N, D] every window's initial state
    t: torch.Tensor,  # [T] the data's times
    first: list[int],  # the full windows' first steps
    index: list[int],  # their places in x0's K
    length: int,
) -> list[tuple[int, torch.Tensor]]:
    """The full windows as one rollout of K·B records (window-major) on the first window's times."""
    device, dtype = x0.device, x0.dtype
    b, k = x0.shape[0], len(first)
    span = torch.tensor(first)[:, None] + torch.arange(length + 1)  # [K, L+1] sample indices
    given = data.inputs(0, None).to(device, dtype)
    u = None if given.u is None else given.u[:, span].transpose(0, 1).flatten(0, 1)  # [K·B, L+1, N, C]
    edges = given.edge_index if given.edge_index.dim() == 2 else given.edge_index.repeat(k, 1, 1)
    feats = given.node_features
    if feats is not None and feats.dim() == 3:
        feats = feats.repeat(k, 1, 1)
    before = past_samples(model, data, first)  # [K, P] or None
    past = None if before is None else data.x.to(device, dtype)[:, before].transpose(0, 1).flatten(0, 1)
    rows = given.meta.get("record_index")  # which recording each row is, window-major (a per-recording gain)
    meta = {**given.meta, "record_index": (torch.arange(b) if rows is None else torch.as_tensor(rows)).repeat(k)}
    inputs = Inputs(edge_index=edges, u=u, node_features=feats, meta=meta, past=past)  # past: [K·B, P, N, D]
    start = x0[:, index].transpose(0, 1).flatten(0, 1)  # [K·B, N, D]
    pred = model.rollout(start, t[first[0] : first[0] + length + 1], inputs)  # [K·B, L+1, N, D]
    return [(s, p) for s, p in zip(first, pred.unflatten(0, (k, b)).unbind(0), strict=True)]


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
