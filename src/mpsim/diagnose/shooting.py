"""Multi-step prediction: window rollouts, held-out window error, and multiple-shooting fits.

A one-step regression screens candidates quickly, but its coefficients inherit whatever the data's own
integrator did within a step (coarse semi-implicit Euler, staggered velocities): biased values, and O(h)
artefacts that look like physics. Here coefficients are fitted by *multiple shooting* through the model's own
integrator — the model (plus the candidate) is rolled out from observed states over windows and compared with
the observations that follow — and candidates are judged by the held-out error of such rollouts.

Windows start every `length` steps at the same step index in every trajectory (one batched rollout per start,
so absolute time stays right for time-dependent terms); the last window may be shorter (`diagnose.windows`).
Errors are on the measured states; with unmeasured ones (`data.observed`) each window's latent start is fitted
(`diagnose.latent`): jointly with the parameters in a fit, with the model fixed on held-out windows.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, cast

import torch
from torch import nn

from mpsim.data.measurement import as_measured
from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.latent import (
    REFRESH_ITERS,
    LatentStarts,
    fit_latent,
    fitted_latent,
    initial_latent,
    latent_jacobian,
    profile_out,
)
from mpsim.diagnose.windows import window_predictions as window_predictions
from mpsim.diagnose.windows import window_residuals
from mpsim.diagnose.windows import window_starts as _starts
from mpsim.errors import DivergenceError
from mpsim.models.base import Model
from mpsim.models.capabilities import Interpretable

#: how a fit, a rollout or the numbers reported from them fail numerically: a rollout that blew up or an ODE solver
#: that gave up (`DivergenceError`), a float overflow (`math.exp` of a parameter fitted in log), a linear-algebra
#: routine on non-finite values. Caught per candidate (`diagnose.trial`): one candidate's failure is its own.
NUMERICAL_FAILURES: tuple[type[Exception], ...] = (
    DivergenceError,
    OverflowError,
    FloatingPointError,
    torch.linalg.LinAlgError,
)


def failure_text(exc: BaseException) -> str:
    """A numerical failure in a few words: the error's first sentence (without the advice on training that an
    ODE solver's failure carries), its kind named when it is not mpsim's own."""
    text = str(exc).split(". ")[0].rstrip(".") or "no message"
    return text if isinstance(exc, DivergenceError) else f"{type(exc).__name__}: {text}"


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


def window_sq_error(model: Model, data: Trajectories, length: int, latent: LatentStarts | None = None) -> torch.Tensor:
    """[B, K, N, D_obs] squared normalised errors of every window step (K = the predicted steps of all windows) on
    the measured states; windows start from the data's states, their latent part from `latent` when given."""
    res, mask = window_residuals(model, data, length, None if latent is None else latent.states(model, data))
    return res[:, mask].pow(2)


@torch.no_grad()
def window_error(model: Model, data: Trajectories, length: int) -> torch.Tensor:
    """[B] mean squared normalised multi-step error per trajectory on the measured states (inf for a trajectory
    whose rollout failed); unmeasured states start each window where they fit its measured samples best, the
    model fixed (state estimation, `diagnose.latent`)."""
    model.eval()
    try:
        latent = fitted_latent(model, data, length)
        err = window_sq_error(model, data, length, latent).double().mean(dim=(1, 2, 3)).cpu()
    except DivergenceError:
        return torch.full((len(data),), math.inf, dtype=torch.float64)
    return torch.where(torch.isfinite(err), err, torch.full_like(err, math.inf))


@torch.no_grad()
def window_errors(model: Model, data: Trajectories, length: int) -> torch.Tensor:
    """[B, K] mean squared normalised error of every window of every trajectory on the measured states (inf for a
    trajectory whose rollout failed): the units of the held-out test (`diagnose.stats.paired`), which weighs
    windows of one record as dependent (`hac_mean`). Latent starts as `window_error`."""
    model.eval()
    try:
        latent = fitted_latent(model, data, length)
        res, mask = window_residuals(model, data, length, None if latent is None else latent.states(model, data))
    except DivergenceError:
        return torch.full((len(data), len(_starts(data.n_times, length))), math.inf, dtype=torch.float64)
    sq = res.double().pow(2).mean(dim=(3, 4)) * mask.to(res.device)  # [B, K, L]
    err = (sq.sum(dim=2) / mask.sum(dim=1).clamp(min=1).to(sq)).cpu()  # [B, K]
    bad = ~torch.isfinite(err).all(dim=1, keepdim=True)  # a record whose rollout failed anywhere: inf throughout
    return torch.where(bad, torch.full_like(err, math.inf), err)


#: held-out records fewer than this are tested window by window (`window_errors`, the windows of a record dependent:
#: `stats.hac_mean`); from this many on, one error per record (Student's t over them is already near the normal's)
PER_WINDOW_BELOW = 8


#: with fewer than `PER_WINDOW_BELOW` held-out records each is cut into at least this many held-out windows (none
#: shorter than `MIN_TEST_WINDOW` steps): four 1 s segments held out of one 25 s record give twelve windows
WINDOWS_PER_RECORD = 3
MIN_TEST_WINDOW = 10


def scored_window(n_records: int, n_times: int, length: int) -> int:
    """Steps of a held-out window: `length` (the horizon), shortened so that each of fewer than `PER_WINDOW_BELOW`
    records gives `WINDOWS_PER_RECORD` windows, but to no fewer than `MIN_TEST_WINDOW` steps."""
    if n_records >= PER_WINDOW_BELOW:
        return length
    whole = -(-(n_times - 1) // WINDOWS_PER_RECORD)  # ceil: no stub of a step or two left at the record's end
    return max(min(length, whole), min(length, MIN_TEST_WINDOW))


def heldout_errors(model: Model, data: Trajectories, length: int, window: int | None = None) -> torch.Tensor:
    """The held-out test's errors over windows of `window` steps (None: `length`, the horizon; see `scored_window`):
    [B, K] per window (`window_errors`) when there are fewer than `PER_WINDOW_BELOW` records, else [B] per record
    (`window_error`). Null records, cut window by window, are scored over the same windows as the data's."""
    steps = length if window is None else min(window, length)
    if len(data) < PER_WINDOW_BELOW:
        return window_errors(model, data, steps)
    return window_error(model, data, steps)


def horizon_from_data(model: Model, data: Trajectories, threshold: float, above_first: float = 0.0) -> int:
    """Steps the model tracks the held-in data from their first states before its normalised rollout error
    exceeds `threshold`, or `above_first` × its error at the first step if that is larger (at least 2; the whole
    record when it never does): short windows for chaotic systems, whole records otherwise."""
    with torch.no_grad():
        try:
            latent = fitted_latent(model, data, data.n_times - 1)  # unmeasured states: their best start
            res, _ = window_residuals(
                model, data, data.n_times - 1, None if latent is None else latent.states(model, data)
            )
        except DivergenceError:
            return 2
        err = torch.cat([res.new_zeros(1), res[:, 0].pow(2).mean(dim=(0, 2, 3)).sqrt()]).cpu()  # [T]
    over = torch.nonzero(~(err <= max(threshold, above_first * float(err[1])))).flatten()
    return data.n_times - 1 if over.numel() == 0 else max(int(over[0]), 2)


@dataclass
class ShootingFit:
    """Result of a multiple-shooting fit.

    Attributes:
        loss: final mean squared normalised window error on the fitting data (measured states).
        values: the fitted values of the free parameters (flattened, in the order given).
        stderr: cluster-robust (by trajectory) standard errors of `values` (Gauss–Newton sandwich).
        converged: whether the fit ended with a finite loss.
        latent: [B, K, N, L] the fitted latent start of every window (raw units), None when every state is
            measured.
        failure: why the fit did not converge ("" when it did): the rollout's failure where it stopped (the
            ODE solver's message), or a non-finite loss. The parameters are then back at their starting values.
        stopped_at: the free parameters' values where the fit failed (flattened as `values`; empty when it
            converged or failed at its start).
    """

    loss: float
    values: list[float]
    stderr: list[float]
    converged: bool
    latent: torch.Tensor | None = None
    failure: str = ""
    stopped_at: list[float] = field(default_factory=list)


def shooting_fit(
    model: Model,
    data: Trajectories,
    length: int,
    free: Sequence[nn.Parameter],
    iters: int = 25,
    stderr: bool = True,
    restarts: int = 1,
) -> ShootingFit:
    """Fit the `free` parameters of `model` (in place) by L-BFGS on the window error of `data`; every other
    parameter stays fixed. Returns the fit with standard errors from the Jacobian of the window residuals.

    With unmeasured states the latent part of every window's start is free too, fitted jointly by variable
    projection (`diagnose.latent`): started from the data's estimate, refreshed for the current parameters at
    every evaluation of the objective. `stderr=False`: no standard errors (nan), for a fit whose values are used
    but never reported (a null fit, the refit of the model's own parameters). `restarts` > 1: L-BFGS starts again
    (with the curvature scales of where it stopped) up to this many times while the loss still falls by more
    than 1 % — for a curved valley such as a delay's τ against the gain and the model's own parameters, where one
    run stops early."""
    free = list(free)
    latent = initial_latent(model, data, length)
    if latent is not None:
        latent = fit_latent(model, data, latent)
    if not free:
        try:
            with torch.no_grad():
                loss = float(window_sq_error(model, data, length, latent).double().mean())
        except DivergenceError as exc:
            return ShootingFit(math.inf, [], [], False, None, failure_text(exc))
        why = "" if math.isfinite(loss) else "the window error is not finite"
        return ShootingFit(loss, [], [], not why, None if latent is None else latent.raw(model), why)
    keep = {id(p): p.requires_grad for p in model.parameters()}
    for p in model.parameters():
        p.requires_grad_(False)
    for p in free:
        p.requires_grad_(True)
    start = [p.detach().clone() for p in free]
    held = [latent]  # the latent starts of the last evaluation (warm start of the next)
    model.train()
    failed: tuple[str, list[float]] | None = None  # (why, where) when a rollout failed during the fit
    try:
        last = math.inf
        for k in range(max(restarts, 1)):  # a handful of L-BFGS runs
            loss = _lbfgs(model, data, length, free, held, iters, measure=k < restarts - 1)
            if not loss < 0.99 * last:
                break
            last = loss
    except DivergenceError as exc:
        failed = (failure_text(exc), _flat(free))
        with torch.no_grad():  # back to where the fit started
            for p, v in zip(free, start, strict=True):
                p.copy_(v)
    finally:
        for p in model.parameters():
            p.requires_grad_(keep.get(id(p), True))
    model.eval()
    return _finish(model, data, length, free, start, failed, stderr)


def _flat(free: list[nn.Parameter]) -> list[float]:
    """The free parameters' current values, flattened in order."""
    return torch.cat([p.detach().reshape(-1).double().cpu() for p in free]).tolist()


def _lbfgs(
    model: Model, data: Trajectories, length: int, free: list[nn.Parameter], held: list, iters: int, measure: bool
) -> float:
    """One L-BFGS run from the free parameters' current values (in place): the loss where it stopped (with
    `measure`, else nan). `held`: the latent starts of the last evaluation (warm start of the next)."""
    scales = curvature_scales(model, data, length, free, held[0])
    start = [p.detach().clone() for p in free]
    # L-BFGS moves z, p = start + scale·z: unit curvature along every parameter, whatever its units (a cubic
    # stiffness of 1e5 in raw units beside a log-mass of 0.7 would otherwise never move)
    zs = [torch.zeros(p.shape, dtype=torch.float64, device=p.device, requires_grad=True) for p in free]
    opt = torch.optim.LBFGS(zs, lr=1.0, max_iter=iters, history_size=20, line_search_fn="strong_wolfe")

    def place() -> None:
        with torch.no_grad():
            for p, p0, s, z in zip(free, start, scales, zs, strict=True):
                p.copy_((p0.double() + s * z.detach()).to(p.dtype))

    def closure() -> torch.Tensor:
        opt.zero_grad(set_to_none=True)
        for p in free:
            p.grad = None
        place()
        try:
            if held[0] is not None:
                held[0] = fit_latent(model, data, held[0], REFRESH_ITERS)
            loss = window_sq_error(model, data, length, held[0]).mean()
        except DivergenceError:
            loss = None
        if loss is None or not torch.isfinite(loss):  # a trial step too far: a bad point the line search leaves
            for z in zs:
                z.grad = torch.zeros_like(z)
            return torch.tensor(1e30, dtype=torch.float64)
        loss.backward()
        for p, s, z in zip(free, scales, zs, strict=True):
            z.grad = torch.zeros_like(z) if p.grad is None else p.grad.double() * s
        return loss.detach().double()

    opt.step(closure)
    place()  # where the line search left z
    if not measure:
        return math.nan
    with torch.no_grad():
        return float(window_sq_error(model, data, length, held[0]).double().mean())


def curvature_scales(
    model: Model,
    data: Trajectories,
    length: int,
    free: list[nn.Parameter],
    latent: LatentStarts | None,
    probes: int = 4,
) -> list[torch.Tensor]:
    """Per entry of every free parameter (float64, its shape): 1/√ of the Gauss–Newton curvature of the mean
    squared window error along it, so that a unit step changes the normalised residuals by about one RMS. The
    diagonal of JᵀJ is estimated from `probes` random ±1 projections of the residuals (Hutchinson: E[(Jᵀv)²] =
    diag JᵀJ), one rollout and `probes` backward passes; an entry the residuals do not feel keeps the scale 1."""
    res, mask = window_residuals(model, data, length, None if latent is None else latent.states(model, data))
    r = res[:, mask]
    gen = torch.Generator().manual_seed(0)
    acc = [torch.zeros(p.shape, dtype=torch.float64, device=p.device) for p in free]
    for k in range(probes):  # a handful of random projections
        v = (torch.randint(0, 2, r.shape, generator=gen) * 2 - 1).to(r)
        grads = torch.autograd.grad((r * v).sum(), free, retain_graph=k < probes - 1, allow_unused=True)
        for a, g in zip(acc, grads, strict=True):
            if g is not None:
                a += g.detach().double().pow(2) / probes
    out = []
    for a in acc:
        curv = 2.0 * a / max(r.numel(), 1)
        good = torch.isfinite(curv) & (curv > 0)
        out.append(torch.where(good, curv.clamp_min(1e-300).rsqrt(), torch.ones_like(curv)))
    return out


def _finish(
    model: Model,
    data: Trajectories,
    length: int,
    free: list[nn.Parameter],
    start: list[torch.Tensor],
    failed: tuple[str, list[float]] | None,
    stderr: bool = True,
) -> ShootingFit:
    """The fit's final loss, values and intervals; back where it started if it failed on the way (`failed`: why
    and where) or ended on a point where the rollout fails or its error is not finite (an L-BFGS line search can
    stop on a point it never evaluated as such: the unmeasured starts are estimated afresh here)."""
    latent = None
    with torch.no_grad():
        try:
            latent = fitted_latent(model, data, length)
            loss = float(window_sq_error(model, data, length, latent).double().mean())
        except DivergenceError as exc:
            loss = math.nan
            failed = failed or (failure_text(exc), _flat(free))
        if failed is None and not math.isfinite(loss):
            failed = (f"the window error is {loss} there", _flat(free))
        if failed is not None:  # ended on a diverging point: back to where the fit started
            for p, v in zip(free, start, strict=True):
                p.copy_(v)
    values = _flat(free)
    if failed is not None:
        return ShootingFit(loss, values, [math.nan] * len(values), False, None, failed[0], failed[1])
    errors = sandwich_stderr(model, data, length, free, latent) if stderr else [math.nan] * len(values)
    return ShootingFit(loss, values, errors, True, None if latent is None else latent.raw(model))


@torch.no_grad()
def sandwich_stderr(
    model: Model, data: Trajectories, length: int, free: list[nn.Parameter], latent: LatentStarts | None = None
) -> list[float]:
    """Standard errors of the free parameters: Gauss–Newton with a sandwich over trajectories (window residuals
    within a trajectory are correlated), the Jacobian by central differences (a handful of parameters). With
    unmeasured states each window's latent start is fitted (`latent`, or here) and its directions are projected
    out of the Jacobian (`diagnose.latent.profile_out`). nan where they cannot be had: a rollout at the fitted
    values or a difference step beside them fails, or the Jacobian is not finite."""
    try:
        return _sandwich(model, data, length, free, latent)
    except NUMERICAL_FAILURES:
        return [math.nan] * sum(p.numel() for p in free)


def _sandwich(
    model: Model, data: Trajectories, length: int, free: list[nn.Parameter], latent: LatentStarts | None
) -> list[float]:
    if latent is None:
        latent = fitted_latent(model, data, length)
    starts = None if latent is None else latent.states(model, data)

    def residuals() -> torch.Tensor:  # [B, K, M] normalised residuals per trajectory and window
        res, _ = window_residuals(model, data, length, starts)
        return res.flatten(2).double().cpu()

    r0 = residuals()
    flat = [(p, i) for p in free for i in range(p.numel())]
    cols = []
    for p, i in flat:  # a handful of parameters
        view = p.data.view(-1)
        h = 1e-6 * max(abs(float(view[i])), 1.0)
        old = float(view[i])
        try:
            view[i] = old + h
            plus = residuals()
            view[i] = old - h
            minus = residuals()
        finally:  # a failed rollout beside the fitted values leaves them as they were
            view[i] = old
        cols.append((plus - minus) / (2 * h))
    jac = torch.stack(cols, dim=-1)  # [B, K, M, P]
    if latent is not None:
        jac_latent = latent_jacobian(model, data, latent).double().cpu()
        if not torch.isfinite(jac_latent).all():  # a pseudo-inverse of non-finite values is no projection
            return [math.nan] * len(flat)
        jac = profile_out(jac, jac_latent)
    jac, r0 = jac.flatten(1, 2), r0.flatten(1)  # [B, K·M, P], [B, K·M]
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
    observed states, on the observed times — measured as the data were: their noise level per state variable
    ([D]) and quantisation step, unmeasured states estimated again (`mpsim.data.measurement.as_measured`). The model's own integration error is then part of the null level, as it is part of its
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
    x = as_measured(pred, data.t, data, noise, gen)
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
    x = as_measured(pred, data.t[: segment + 1], data, noise, gen)
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
