"""Free-run simulation of whole records, the field's yardstick: each test record simulated from its first samples
to its end, open loop, driven by its measured inputs, and scored on the measured channels after the samples that
started it (RMSE in the signal's units, NRMSE, fit %).

Two steps, both batched over the records:

- **The start.** The measured states come from the first sample; the latent ones (``Trajectories.latent_index``)
  start at the data's estimate (those only the model can estimate, ``meta['pending']``: its smoother over the first
  `init_samples` samples alone, `mpsim.models.latent`) and are then fitted to the first `init_samples` samples of
  the measured channels (Levenberg–Marquardt, the model fixed: a state estimate, not a parameter fit). The default `init_samples` is
  what the latent states need, 1 + 2·(latent states per node), at least 3 (1 when every state is measured), and
  the summary states it.
- **The run.** Simulated in chunks of `chunk` samples, all chunks of all records in one batched rollout, each from
  the end of the one before in the previous pass (parareal): a pass makes at least one more chunk exact, and a
  stable system's chunks agree with their neighbours after a few passes. Passes stop when no chunk's start moves by
  more than `tol` of the state's scale (normalised units), after at most as many passes as chunks, when the result
  is the sequential run's. A model that reads time or carries a latent state (MP-NODE messages) runs each record in
  one rollout instead.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import Any

import torch

from mpsim.data.trajectories import Inputs, Trajectories
from mpsim.errors import ConfigError, DivergenceError
from mpsim.models.base import Model
from mpsim.models.capabilities import LatentState
from mpsim.models.latent import estimate_pending
from mpsim.solvers.odeint import ODESolver

#: samples per chunk of a chunked free run
CHUNK = 1000
#: fixed RK4 steps per sample of a free run (the model's own solver when it has none)
SUBSTEPS = 4
#: a chunked run has converged when no chunk's start moved more than this (normalised units) in the last pass
TOL = 1e-7
#: Levenberg–Marquardt iterations of the latent start
START_ITERS = 20


@dataclass(frozen=True)
class FreeRun:
    """A free run of whole records and its scores.

    Attributes:
        pred: [R, T, N, D] simulated states (raw units; after a record's length, the padding's continuation).
        init_samples: the samples per record that started the run (not scored).
        passes: the chunked run's passes (0: each record in one rollout).
        diverged: [R] whether the record's run became NaN/inf (its scores are NaN).
        scores: per record, {channel: {"rmse", "nrmse", "fit", "samples"}} over the scored samples.
    """

    pred: torch.Tensor
    init_samples: int
    passes: int
    diverged: list[bool]
    scores: list[dict[str, dict[str, float]]] = field(default_factory=list)


def default_init_samples(records: Trajectories) -> int:
    """The samples that start a free run: 1 when every state is measured, else 1 + 2·L (L latent states per
    node), at least 3."""
    latent = len(records.latent_index)
    return 1 if latent == 0 else max(3, 1 + 2 * latent)


def free_run(
    model: Model,
    records: Trajectories,
    init_samples: int | None = None,
    chunk: int = CHUNK,
    tol: float = TOL,
    substeps: int | None = SUBSTEPS,
) -> FreeRun:
    """Simulate every record of `records` ([R, T, N, D], whole records padded after their ends, ``meta['records']``
    their lengths) from its start to its end and score it (module docstring). A model integrated by an ODE solver
    runs with fixed-step RK4, `substeps` steps per sample (None: its own solver): an adaptive solver batched over
    chunks would choose its steps for all of them at once, so a chunk's run would depend on the others'."""
    n = default_init_samples(records) if init_samples is None else int(init_samples)
    lengths = [int(e["length"]) for e in records.meta.get("records", [])] or [records.n_times] * len(records)
    if n < 1 or n >= min(lengths):
        raise ConfigError(
            f"eval.init_samples={n}: give at least 1 and fewer than the shortest test record's {min(lengths)} samples."
        )
    device, dtype = model.state_mean.device, model.state_mean.dtype
    data = records.to(device, dtype)
    with torch.no_grad(), _fixed_steps(model, float(records.t[1] - records.t[0]), substeps):
        x0 = _start(model, data, n)
        pred, passes, diverged = _run(model, data, x0, chunk, tol)
    pred = pred.cpu()
    scores = [score_record(pred[r], records.x[r], records, n, lengths[r]) for r in range(len(records))]
    return FreeRun(pred=pred, init_samples=n, passes=passes, diverged=diverged, scores=scores)


def score_record(
    pred: torch.Tensor,  # [T, N, D] one record's simulation
    true: torch.Tensor,  # [T, N, D] its data
    records: Trajectories,
    start: int,
    length: int,
) -> dict[str, dict[str, float]]:
    """{measured channel: {"rmse", "nrmse", "fit", "samples"}} over samples start..length−1 of one record, pooled
    over nodes: RMSE in raw units, NRMSE = RMSE / std of the data, fit % = 100·(1 − ‖y − ŷ‖ / ‖y − ȳ‖)."""
    out = {}
    names = records.state_names
    for d in records.observed_index:  # a loop over the few measured channels
        y = true[start:length, :, d].double()
        e = pred[start:length, :, d].double() - y
        rmse = float(e.pow(2).mean().sqrt())
        spread = float((y - y.mean()).pow(2).mean().sqrt())
        finite = math.isfinite(rmse)
        out[names[d]] = {
            "rmse": rmse if finite else float("nan"),
            "nrmse": rmse / spread if finite and spread > 0 else float("nan"),
            "fit": 100.0 * (1.0 - rmse / spread) if finite and spread > 0 else float("nan"),
            "samples": int(length - start),
        }
    return out


def _start(model: Model, data: Trajectories, n: int) -> torch.Tensor:  # -> [R, N, D]
    """Every record's initial state: measured states from its first sample, latent ones fitted to its first `n`
    samples by Levenberg–Marquardt (batched over records; finite differences, one rollout per iteration)."""
    if data.meta.get("pending"):  # latent states only the model can estimate: from the first n samples alone
        first = replace(
            data, t=data.t[: max(n, 2)], x=data.x[:, : max(n, 2)], u=None if data.u is None else data.u[:, : max(n, 2)]
        )
        data = replace(data, x=torch.cat([estimate_pending(model, first).x.to(data.x), data.x[:, max(n, 2) :]], dim=1))
    x0 = data.x[:, 0].clone()
    latent, observed = data.latent_index, data.observed_index
    if not latent or n < 2:
        return x0
    scale = model.state_std[latent]  # [L] normalised units for the latent components
    t = data.t[:n]
    r_, big = len(data), data.x.shape[2] * len(latent)
    damping = torch.full((r_,), 1e-3, dtype=x0.dtype, device=x0.device)

    def residuals(z: torch.Tensor) -> torch.Tensor:  # z: [M, R, N, L] latent starts -> [M, R, n·N·O]
        m = z.shape[0]
        starts = x0.expand(m, *x0.shape).clone()
        starts[..., latent] = z
        inputs = _repeat(data.inputs(0, n), m)
        out = model.rollout(starts.reshape(m * r_, *x0.shape[1:]), t, inputs)
        err = (out.reshape(m, r_, n, *x0.shape[1:]) - data.x[:, :n])[..., observed] / model.state_std[observed]
        return err.reshape(m, r_, -1)

    z = x0[..., latent].clone()  # [R, N, L]
    eye = torch.eye(big, dtype=x0.dtype, device=x0.device).reshape(big, *z.shape[1:]) * scale * 1e-4
    cost = residuals(z[None])[0].pow(2).sum(-1)  # [R]
    for _ in range(START_ITERS):  # iterations of one batched solve over every record
        probes = torch.cat([z[None], z[None] + eye[:, None]], dim=0)  # [1 + big, R, N, L]
        res = residuals(probes)
        r0, jac = res[0], ((res[1:] - res[0]) / 1e-4).permute(1, 2, 0)  # [R, M], [R, M, big]
        if not (torch.isfinite(jac).all() and torch.isfinite(r0).all()):
            break
        a = jac.mT @ jac
        g = (jac.mT @ r0[..., None])[..., 0]
        diag = torch.diag_embed(a.diagonal(dim1=-2, dim2=-1).clamp_min(1e-12))
        step = -torch.linalg.solve(a + damping[:, None, None] * diag, g[..., None])[..., 0]  # [R, big] (scaled)
        trial = z + step.reshape(z.shape) * scale
        new_cost = residuals(trial[None])[0].pow(2).sum(-1)
        better = torch.isfinite(new_cost) & (new_cost < cost)
        z = torch.where(better[:, None, None], trial, z)
        if float(step.abs().max()) < 1e-8 or not bool(better.any()):
            break
        cost = torch.where(better, new_cost, cost)
        damping = torch.where(better, damping * 0.3, damping * 10.0)
    x0[..., latent] = z
    return x0


@contextmanager
def _fixed_steps(model: Model, dt: float, substeps: int | None) -> Iterator[None]:
    """`model` integrated by RK4 at `substeps` steps per sample of `dt` while inside (its own solver after)."""
    own = getattr(model, "solver", None)
    if substeps is None or not isinstance(own, ODESolver):
        yield
        return
    model.solver = ODESolver("rk4", step_size=dt / int(substeps))  # type: ignore[assignment]
    try:
        yield
    finally:
        model.solver = own  # type: ignore[assignment]


def _repeat(inputs: Inputs, m: int) -> Inputs:
    """`inputs` for `m` copies of its batch, stacked along B (copy-major)."""
    u = None if inputs.u is None else inputs.u.repeat(m, *([1] * (inputs.u.dim() - 1)))
    edges = inputs.edge_index if inputs.edge_index.dim() == 2 else inputs.edge_index.repeat(m, 1, 1)
    nf = inputs.node_features
    if nf is not None and nf.dim() == 3:
        nf = nf.repeat(m, 1, 1)
    return replace(inputs, u=u, edge_index=edges, node_features=nf, past=None)


def _run(
    model: Model, data: Trajectories, x0: torch.Tensor, chunk: int, tol: float
) -> tuple[torch.Tensor, int, list[bool]]:
    """[R, T, N, D] the free run from `x0` ([R, N, D]): chunked (parareal) when the model allows, else whole."""
    steps = data.n_times - 1
    per_record = any(getattr(e, "per_record", False) for e in model.effects)  # chunks would reorder the records
    if steps <= chunk or not model.time_invariant or isinstance(model, LatentState) or per_record:
        return _finite(_whole(model, data, x0), 0)
    k = math.ceil(steps / chunk)
    pad = k * chunk - steps
    u = data.u
    if u is not None and pad:
        u = torch.cat([u, u[:, -1:].expand(-1, pad, *u.shape[2:])], dim=1)
    u_chunks = None if u is None else u.unfold(1, chunk + 1, chunk).permute(1, 0, 4, 2, 3)  # [K, R, C+1, N, C']
    x_guess = data.x
    if pad:
        x_guess = torch.cat([x_guess, x_guess[:, -1:].expand(-1, pad, *x_guess.shape[2:])], dim=1)
    starts = x_guess[:, ::chunk][:, :k].permute(1, 0, 2, 3).clone()  # [K, R, N, D] from the data's states
    starts[0] = x0
    t = data.t[: chunk + 1] - data.t[0]
    inputs = Inputs(
        edge_index=data.edge_index if data.edge_index.dim() == 2 else data.edge_index.repeat(k, 1, 1),
        u=None if u_chunks is None else u_chunks.reshape(-1, *u_chunks.shape[2:]),
        node_features=data.node_features,
        meta=data.meta,
    )
    scale = model.state_std
    out = None
    passes = 0
    while passes < k:  # passes of the parareal iteration; each makes at least one more chunk exact
        passes += 1
        try:
            flat = model.rollout(starts.reshape(-1, *starts.shape[2:]), t, inputs)
        except DivergenceError:  # a chunk the solver cannot finish: the records whole, one at a time if need be
            return _finite(_whole(model, data, x0), 0)
        out = flat.reshape(k, len(data), chunk + 1, *x0.shape[1:])
        new = torch.cat([x0[None], out[:-1, :, -1]], dim=0)
        moved = ((new - starts) / scale).abs().nan_to_num(nan=math.inf).amax()
        starts = new
        if float(moved) <= tol:
            break
    assert out is not None
    body = out[:, :, :-1].permute(1, 0, 2, 3, 4).reshape(len(data), k * chunk, *x0.shape[1:])
    return _finite(torch.cat([body, out[-1, :, -1:]], dim=1)[:, : data.n_times], passes)


def _finite(pred: torch.Tensor, passes: int) -> tuple[torch.Tensor, int, list[bool]]:  # pred: [R, T, N, D]
    """(pred, passes, whether each record's run became NaN/inf)."""
    return pred, passes, [not bool(torch.isfinite(p).all()) for p in pred]


def _whole(model: Model, data: Trajectories, x0: torch.Tensor) -> torch.Tensor:  # -> [R, T, N, D]
    """Each record in one rollout (all at once; one at a time if the batch fails, a failed one NaN)."""
    try:
        return model.rollout(x0, data.t - data.t[0], data.inputs())
    except DivergenceError:
        outs = []
        for r in range(len(data)):  # a loop over the records, only after the batched rollout failed
            part = data.subset([r])
            try:
                outs.append(model.rollout(x0[r : r + 1], data.t - data.t[0], part.inputs()))
            except DivergenceError:
                outs.append(torch.full_like(part.x, float("nan")))
        return torch.cat(outs)


def summary_of(run: FreeRun, records: Trajectories) -> dict[str, Any]:
    """What summary.json keeps of a free run: per record its file, start, scored samples and per channel RMSE,
    NRMSE and fit %; and the mean over records per channel."""
    entries = records.meta.get("records", [])
    rows = []
    for r, scores in enumerate(run.scores):
        e = entries[r] if r < len(entries) else {}
        rows.append(
            {
                "record": str(e.get("recording", f"record {r}")),
                "t0": e.get("t0"),
                "length": e.get("length", records.n_times),
                "diverged": run.diverged[r],
                "channels": scores,
            }
        )
    channels = sorted({c for s in run.scores for c in s})
    mean = {
        c: {k: float(torch.tensor([s[c][k] for s in run.scores if c in s]).mean()) for k in ("rmse", "nrmse", "fit")}
        for c in channels
    }
    return {"init_samples": run.init_samples, "passes": run.passes, "records": rows, "mean": mean}
