"""Latent states of any kind, estimated through the model: a state that is no derivative of anything measured (an
upper tank's level, a drive's current; every state of a belt drive whose sensor reads |speed|) is filled by the
unscented Kalman smoother (`mpsim.estimate`) over the nominal model's own one-sample step and its outputs.

The data pipeline leaves such states as zeros and lists them in ``meta['pending']`` (it has no model); once the
model is built, `estimate_pending` runs the smoother on every trajectory (segment or record) of a split:

- the smoother's state is the spec's states at every node (the outputs are computed from them);
- its step is the model's rollout over one sample (its own solver, the inputs held as the data say);
- what it compares are the measured columns (`Trajectories.observed_index`), with the noise each channel's data
  show (``meta['noise']``: level and quantisation step) as R;
- the process noise Q is diagonal, each state's share scaled by its spread in a nominal run of the model, and its
  overall scale chosen by the measurements' likelihood (`choose_process_noise`);
- a trajectory longer than `MAX_SAMPLES` is smoothed over its first `MAX_SAMPLES` samples, its other samples
  taking the nominal run from there (a window of a long record is fitted on its own measured samples later).

The estimate replaces the zeros, and ``meta['estimated']`` says how, with the smoother's mean spread (1σ) per state.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import torch

from mpsim.data.trajectories import Trajectories
from mpsim.errors import ConfigError, DivergenceError
from mpsim.estimate import choose_process_noise
from mpsim.models.base import Model

#: samples of a long record the smoother reads (the start of a free run)
MAX_SAMPLES = 1000
#: scales of the process noise tried, relative to each state's nominal spread per sample
GRID = (1e-6, 1e-4, 1e-2, 1.0)


def estimate_pending(model: Model, data: Trajectories, iterations: int = 2) -> Trajectories:
    """`data` with its pending latent states (``meta['pending']``) estimated through `model` (module docstring)."""
    pending = list(data.meta.get("pending") or [])
    if not pending or len(data) == 0:
        return data
    spec = getattr(model, "spec", None)
    if spec is None:
        raise ConfigError(
            f"the states {pending} are not measured and no measured state is their rate, so they are estimated "
            "through the model's equations: that needs model=equations (a spec)."
        )
    names = data.state_names
    n_states = len(spec.states)
    cols = [names.index(s) for s in spec.states]
    device, dtype = model.state_mean.device, model.state_mean.dtype
    part = data.to(device, dtype)
    length = min(part.n_times, MAX_SAMPLES)
    with torch.no_grad():
        smoothed, scale = _smooth(model, part, length, n_states, iterations)
    x = part.x.clone()
    b, _, n, _ = x.shape
    mean = smoothed.mean.reshape(b, length, n, n_states)
    std = smoothed.std.reshape(b, length, n, n_states)
    index = [names.index(s) for s in pending]
    x[:, :length, :, index] = mean[..., [spec.states.index(s) for s in pending]]
    if part.n_times > length:  # the rest of a long record: the nominal run from the smoother's last state
        start = x[:, length - 1].clone()
        start[..., cols] = mean[:, -1]
        with torch.no_grad():
            tail = model.rollout(start, part.t[length - 1 :] - part.t[length - 1], part.inputs(length - 1))
        x[:, length:, :, index] = tail[:, 1:, :, index]
    spread = {s: float(std[..., spec.states.index(s)].mean()) for s in pending}
    how = {
        s: f"unscented Kalman smoother over the nominal model (process noise ×{scale:.3g}; mean 1σ spread "
        f"{spread[s]:.3g})"
        for s in pending
    }
    meta = {**data.meta, "estimated": {**data.meta.get("estimated", {}), **how}, "spread": spread}
    meta.pop("pending", None)
    return replace(data, x=x.to(data.x.dtype).cpu(), meta=meta)


def _smooth(model: Model, data: Trajectories, length: int, n_states: int, iterations: int) -> tuple[Any, float]:
    """The smoother's result over the first `length` samples of every trajectory, and the process-noise scale."""
    b, _, n, d = data.x.shape
    observed = data.observed_index
    t = data.t[:length] - data.t[0]
    u = None if data.u is None else data.u[:, :length]
    measured = data.x[:, :length][..., observed].reshape(b, length, -1)  # [B, T, N·O]

    def columns(z: torch.Tensor, k: int, rows: int) -> torch.Tensor:  # z: [B·R, N, S] -> [B·R, N, D]
        full = z.new_zeros(z.shape[0], n, d)
        full[..., :n_states] = z
        if d > n_states:  # a spec with outputs: read them from the states at sample k
            step_u = None if u is None else u[:, k : k + 1].repeat_interleave(rows, dim=0)
            outputs_of: Any = model.outputs_of  # a spec's model (`EquationsModel`)
            outs = outputs_of(z[:, None], t[k : k + 1], replace(data.inputs(), u=step_u))
            full[..., n_states:] = outs[:, 0]
        return full

    def step(x: torch.Tensor, k: int) -> torch.Tensor:  # x: [B, R, N·S] -> [B, R, N·S]
        rows = x.shape[1]
        z = x.reshape(b * rows, n, n_states)
        step_u = None if u is None else u[:, k : k + 2].repeat_interleave(rows, dim=0)
        inputs = replace(data.inputs(), u=step_u)
        out = model.rollout(columns(z, k, rows), t[k : k + 2] - t[k], inputs)[:, 1, :, :n_states]
        return out.reshape(b, rows, n * n_states)

    def output(x: torch.Tensor, k: int) -> torch.Tensor:  # x: [B, R, N·S] -> [B, R, N·O]
        rows = x.shape[1]
        full = columns(x.reshape(b * rows, n, n_states), k, rows)
        return full[..., observed].reshape(b, rows, -1)

    level, spread = _nominal(model, data, length, n_states)  # [N·S] each
    P0 = torch.diag(spread**2)
    Q = torch.diag((spread / max(length, 1) ** 0.5) ** 2)
    R = torch.diag(_noise_variance(data, measured))
    mask = _measured_mask(data, n_states, n)
    x0 = data.x[:, 0, :, :n_states].reshape(b, -1) * mask + level * (1 - mask)
    try:
        choice = choose_process_noise(step, output, measured, x0, P0, Q, R, "ukf", iterations, grid=GRID, refine=1)
    except DivergenceError as err:
        raise DivergenceError(f"estimating the latent states through the model failed: {err}") from None
    return choice.smoothed, choice.scale


def _nominal(model: Model, data: Trajectories, length: int, n_states: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Each state's level (mean) and spread (std, at least a tenth of the level) in a run of the model from the
    data's first samples (latent states at rest) over their inputs, pooled over trajectories: the smoother's prior
    and the scale of its process noise (0 and 1 where the run fails or stays still)."""
    start = data.x[:, 0].clone()
    start[..., [i for i in range(n_states) if i not in data.observed_index]] = 0.0
    n = data.x.shape[2]
    try:
        run = model.rollout(start, data.t[:length] - data.t[0], data.inputs(0, length))[..., :n_states]
        level, spread = run.mean(dim=(0, 1)).reshape(-1), run.std(dim=(0, 1)).reshape(-1)
    except DivergenceError:
        level = torch.zeros(n * n_states, dtype=data.x.dtype, device=data.x.device)
        spread = torch.ones_like(level)
    ok = torch.isfinite(level) & torch.isfinite(spread)
    level = torch.where(ok, level, torch.zeros_like(level))
    spread = torch.where(ok, torch.maximum(spread, 0.1 * level.abs()), torch.ones_like(spread))
    return level, torch.where(spread > 1e-12, spread, torch.ones_like(spread))


def _measured_mask(data: Trajectories, n_states: int, n: int) -> torch.Tensor:  # -> [N·S] 1 where measured
    mask = torch.zeros(n, n_states, dtype=data.x.dtype, device=data.x.device)
    for d in data.observed_index:
        if d < n_states:
            mask[:, d] = 1.0
    return mask.reshape(-1)


def _noise_variance(data: Trajectories, measured: torch.Tensor) -> torch.Tensor:  # measured: [B, T, P] -> [P]
    """Each measured channel's noise variance: its level² + quantum²/12 from the data (`meta['noise']`), at least
    1e-8 of its variance."""
    noise = data.meta.get("noise") or {}
    names = [data.state_names[d] for d in data.observed_index]
    n = data.x.shape[2]
    out = []
    for name in names:  # a loop over the few measured channels
        info = noise.get(name) or {}
        level = float(info.get("std") or 0.0) ** 2 + float(info.get("quantum") or 0.0) ** 2 / 12
        out.append(level)
    var = torch.tensor(out, dtype=measured.dtype, device=measured.device).repeat(n)
    floor = 1e-8 * measured.reshape(-1, measured.shape[-1]).var(dim=0).clamp_min(1e-30)
    return torch.maximum(var, floor)
