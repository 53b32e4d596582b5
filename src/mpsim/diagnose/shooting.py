"""Multi-step prediction: window rollouts, held-out window error, and multiple-shooting fits.

A one-step regression screens candidates quickly, but its coefficients inherit whatever the data's own
integrator did within a step (coarse semi-implicit Euler, staggered velocities): biased values, and O(h)
artefacts that look like physics. Here coefficients are fitted by *multiple shooting* through the model's own
integrator — the model (plus the candidate) is rolled out from observed states over windows and compared with
the observations that follow — and candidates are judged by the held-out error of such rollouts.

Windows start every `length` steps at the same step index in every trajectory (one batched rollout per start,
so absolute time stays right for time-dependent terms); the last window may be shorter.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, cast

import torch
from torch import nn

from mpsim.data.trajectories import Trajectories
from mpsim.errors import DivergenceError
from mpsim.models.base import Model
from mpsim.models.capabilities import Interpretable


def own_parameters(model: Model) -> list[nn.Parameter]:
    """The interpretable parameters a multiple-shooting fit refits beside a candidate: the physical parameters of
    a white-box model (`model=equations`, `model=physics`), the discovered coefficients ξ of an equation-discovery
    model (S-MNN), else none (a network's weights are refit by the finetune of `fix=true`)."""
    raw = getattr(model, "raw", None)
    if isinstance(raw, nn.ParameterDict):
        return list(raw.values())
    theta = getattr(model, "theta", None)
    if isinstance(theta, nn.Parameter) and isinstance(model, Interpretable) and model.sensitivity_names():
        return [theta]
    return []


def _starts(n_times: int, length: int) -> list[int]:
    return list(range(0, n_times - 1, max(length, 1)))


def window_predictions(model: Model, data: Trajectories, length: int) -> list[tuple[int, torch.Tensor]]:
    """[(start, [B, L+1, N, D] rollout from x[:, start] over the next ≤ length steps)], gradients kept."""
    device, dtype = model.state_mean.device, model.state_mean.dtype
    x = data.x.to(device=device, dtype=dtype)
    t = data.t.to(device=device, dtype=dtype)
    out = []
    for s in _starts(data.n_times, length):  # sequential in time only; each rollout batches every trajectory
        end = min(s + length, data.n_times - 1)
        out.append((s, model.rollout(x[:, s], t[s : end + 1], data.inputs(s, end + 1).to(device, dtype))))
    return out


def window_sq_error(model: Model, data: Trajectories, length: int) -> torch.Tensor:
    """[B, K, N, D] squared normalised errors of every window step (K = the predicted steps of all windows)."""
    std = model.state_std.detach()
    parts = []
    for s, pred in window_predictions(model, data, length):
        true = data.x[:, s : s + pred.shape[1]].to(pred)
        parts.append(((pred[:, 1:] - true[:, 1:]) / std).pow(2))
    return torch.cat(parts, dim=1)


@torch.no_grad()
def window_error(model: Model, data: Trajectories, length: int) -> torch.Tensor:
    """[B] mean squared normalised multi-step error per trajectory (inf for a trajectory whose rollout failed)."""
    model.eval()
    try:
        err = window_sq_error(model, data, length).double().mean(dim=(1, 2, 3)).cpu()
    except DivergenceError:
        return torch.full((len(data),), math.inf, dtype=torch.float64)
    return torch.where(torch.isfinite(err), err, torch.full_like(err, math.inf))


def horizon_from_data(model: Model, data: Trajectories, threshold: float) -> int:
    """Steps the model tracks the held-in data from their first states before its normalised rollout error
    exceeds `threshold` (at least 2; the whole record when it never does): short windows for chaotic systems,
    whole records otherwise."""
    with torch.no_grad():
        try:
            ((_, pred),) = window_predictions(model, data, data.n_times - 1)
        except DivergenceError:
            return 2
        std = model.state_std.detach()
        err = ((pred - data.x.to(pred)) / std).pow(2).mean(dim=(0, 2, 3)).sqrt().cpu()  # [T]
    over = torch.nonzero(~(err <= threshold)).flatten()
    return data.n_times - 1 if over.numel() == 0 else max(int(over[0]), 2)


@dataclass
class ShootingFit:
    """Result of a multiple-shooting fit.

    Attributes:
        loss: final mean squared normalised window error on the fitting data.
        values: the fitted values of the free parameters (flattened, in the order given).
        stderr: cluster-robust (by trajectory) standard errors of `values` (Gauss–Newton sandwich).
        converged: whether the fit ended with a finite loss.
    """

    loss: float
    values: list[float]
    stderr: list[float]
    converged: bool


def shooting_fit(
    model: Model,
    data: Trajectories,
    length: int,
    free: Sequence[nn.Parameter],
    iters: int = 25,
) -> ShootingFit:
    """Fit the `free` parameters of `model` (in place) by L-BFGS on the window error of `data`; every other
    parameter stays fixed. Returns the fit with standard errors from the Jacobian of the window residuals."""
    free = list(free)
    if not free:
        with torch.no_grad():
            loss = float(window_error(model, data, length).mean())
        return ShootingFit(loss, [], [], math.isfinite(loss))
    keep = {id(p): p.requires_grad for p in model.parameters()}
    for p in model.parameters():
        p.requires_grad_(False)
    for p in free:
        p.requires_grad_(True)
    opt = torch.optim.LBFGS(free, lr=1.0, max_iter=iters, history_size=20, line_search_fn="strong_wolfe")
    start = [p.detach().clone() for p in free]

    def closure() -> torch.Tensor:
        opt.zero_grad(set_to_none=True)
        try:
            loss = window_sq_error(model, data, length).mean()
        except DivergenceError:
            loss = None
        if loss is None or not torch.isfinite(loss):  # a trial step too far: a bad point the line search leaves
            for p in free:
                p.grad = torch.zeros_like(p)
            return torch.tensor(1e30, dtype=torch.float64)
        loss.backward()
        return loss

    model.train()
    ok = True
    try:
        opt.step(closure)
    except DivergenceError:
        ok = False
        with torch.no_grad():  # back to where the fit started
            for p, v in zip(free, start, strict=True):
                p.copy_(v)
    finally:
        for p in model.parameters():
            p.requires_grad_(keep.get(id(p), True))
    model.eval()
    with torch.no_grad():
        loss = float(window_error(model, data, length).mean())
        if not math.isfinite(loss):  # ended on a diverging point: back to where the fit started
            ok = False
            for p, v in zip(free, start, strict=True):
                p.copy_(v)
    values = torch.cat([p.detach().reshape(-1).double().cpu() for p in free])
    stderr = sandwich_stderr(model, data, length, free) if ok and math.isfinite(loss) else [math.nan] * len(values)
    return ShootingFit(loss, values.tolist(), stderr, ok and math.isfinite(loss))


@torch.no_grad()
def sandwich_stderr(model: Model, data: Trajectories, length: int, free: list[nn.Parameter]) -> list[float]:
    """Standard errors of the free parameters: Gauss–Newton with a sandwich over trajectories (window residuals
    within a trajectory are correlated), the Jacobian by central differences (a handful of parameters)."""

    def residuals() -> torch.Tensor:  # [B, M] normalised residuals per trajectory
        std = model.state_std.detach()
        parts = []
        for s, pred in window_predictions(model, data, length):
            true = data.x[:, s : s + pred.shape[1]].to(pred)
            parts.append(((pred[:, 1:] - true[:, 1:]) / std).reshape(len(data), -1))
        return torch.cat(parts, dim=1).double().cpu()

    r0 = residuals()
    flat = [(p, i) for p in free for i in range(p.numel())]
    cols = []
    for p, i in flat:  # a handful of parameters
        view = p.data.view(-1)
        h = 1e-6 * max(abs(float(view[i])), 1.0)
        old = float(view[i])
        view[i] = old + h
        plus = residuals()
        view[i] = old - h
        minus = residuals()
        view[i] = old
        cols.append((plus - minus) / (2 * h))
    jac = torch.stack(cols, dim=-1)  # [B, M, P]
    if not torch.isfinite(jac).all():
        return [math.nan] * len(flat)
    bread = torch.linalg.pinv(jac.reshape(-1, len(flat)).T @ jac.reshape(-1, len(flat)))
    scores = torch.einsum("bmp,bm->bp", jac, r0)  # [B, P] per-trajectory score
    meat = scores.T @ scores
    b = len(data)
    cov = bread @ meat @ bread * (b / max(b - 1, 1))
    # the coefficients' own scale when the fit is exact (clean data): never report a zero-width interval
    return [float(v) for v in cov.diagonal().clamp(min=0).sqrt()]


def precise(model: Model) -> Model:
    """A float64 copy of `model` integrated with tight tolerances (dopri5, rtol 1e-9): its vector field solved
    exactly, so data made with it carry none of the model's own integration error."""
    from mpsim.solvers.odeint import ODESolver

    ref = copy.deepcopy(model).double()
    if isinstance(getattr(ref, "solver", None), ODESolver):
        cast(Any, ref).solver = ODESolver("dopri5", rtol=1e-9, atol=1e-10, max_num_steps=100_000)
    return ref


def null_data(
    model: Model, data: Trajectories, noise: torch.Tensor, seed: int, segment: int | None = None
) -> Trajectories:
    """Data the model's equations would produce — the exact solution of its vector field (`precise`) from
    observed states, on the observed times — plus Gaussian measurement noise of the given level per state
    variable ([D]). The model's own integration error is then part of the null level, as it is part of its
    error on real data.

    With `segment` shorter than the records (a chaotic system, whose errors are judged over short windows),
    every window of `segment` steps is simulated from its own observed first state and becomes one null
    record (B·K records of `segment` + 1 samples, on the times of the first window): a whole-record simulation
    would leave the data's attractor, and a model with a latent state (MP-NODE messages) restarts it at every
    window, as its windowed predictions do."""
    model = precise(model)
    if segment is not None and segment < data.n_times - 1:
        return _segment_null(model, data, noise, seed, segment)
    with torch.no_grad():
        try:
            ((_, pred),) = window_predictions(model, data, data.n_times - 1)
        except DivergenceError:
            pred = data.x.clone().to(model.state_mean)
    gen = torch.Generator().manual_seed(int(seed))
    eps = torch.randn(pred.shape, generator=gen, dtype=torch.float64) * noise.double()
    x = (pred.double().cpu() + eps).nan_to_num()
    return Trajectories(
        t=data.t, x=x, edge_index=data.edge_index, u=data.u, node_features=data.node_features, meta=data.meta
    )


def _segment_null(model: Model, data: Trajectories, noise: torch.Tensor, seed: int, segment: int) -> Trajectories:
    with torch.no_grad():
        try:
            windows = [(s, p) for s, p in window_predictions(model, data, segment) if p.shape[1] == segment + 1]
        except DivergenceError:
            windows = [(s, data.x[:, s : s + segment + 1].to(model.state_mean)) for s in _starts(data.n_times, segment)]
            windows = [(s, p) for s, p in windows if p.shape[1] == segment + 1]
    k = len(windows)
    pred = torch.cat([p.double().cpu() for _, p in windows], dim=0)  # [K·B, L+1, N, D], window-major
    gen = torch.Generator().manual_seed(int(seed))
    x = (pred + torch.randn(pred.shape, generator=gen, dtype=torch.float64) * noise.double()).nan_to_num()
    u = None if data.u is None else torch.cat([data.u[:, s : s + segment + 1] for s, _ in windows], dim=0)
    feats = data.node_features
    if feats is not None and feats.dim() == 3:
        feats = feats.repeat(k, 1, 1)
    edges = data.edge_index if data.shared_graph else data.edge_index.repeat(k, 1, 1)
    return Trajectories(t=data.t[: segment + 1], x=x, edge_index=edges, u=u, node_features=feats, meta=data.meta)


def with_effect(model: Model, effect: nn.Module) -> Model:
    """A copy of `model` that also carries `effect` (in the model's dtype)."""
    trial = copy.deepcopy(model)
    trial.effects.append(effect.to(dtype=model.state_mean.dtype, device=model.state_mean.device))
    return trial
