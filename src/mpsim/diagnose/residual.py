"""Residuals of a trained model on trajectories, in the data's own time-stepping.

The one-step residual r_k = (x_{k+1} − Φθ(x_k; t_k → t_{k+1})) / Δ compares each observed step with the
model's own step from the observed state, so the model's integrator error cancels and no derivative has to
be estimated from noisy data (finite-difference derivatives are biased: reference/ecosystem_notes.md §D).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from mpsim.data.trajectories import Inputs, Trajectories
from mpsim.errors import ConfigError, DivergenceError
from mpsim.models.base import Model
from mpsim.models.capabilities import one_step


@dataclass
class Residual:
    """One-step residuals of a model on a set of trajectories.

    Attributes:
        r: [B, T−1, N, D] residual per step, raw units per unit time.
        pred: [B, T−1, N, D] the model's one-step predictions of x_{k+1}.
        t_mid: [T−1] step midpoints (where a step's residual is best attributed in time).
        dt: [T−1] step sizes.
    """

    r: torch.Tensor
    pred: torch.Tensor
    t_mid: torch.Tensor
    dt: torch.Tensor


def one_step_residual(model: Model, data: Trajectories, batch_size: int = 1024) -> Residual:
    """Residual of `model` over every step of every trajectory of `data` (float64, no gradients).

    Each step is a batched one-step rollout of all trajectories from the observed state at its absolute
    time, so time-dependent terms (periodic forcing) are evaluated at the right phase; a model's latent state
    (MP-NODE messages) is carried along the observed trajectory (see `mpsim.models.capabilities.one_step`).
    """
    if model.context_steps != 1:
        raise ConfigError(
            f"{type(model).__name__} reads a window of {model.context_steps} states; the one-step "
            "residual needs a model that steps from a single state."
        )
    device, dtype = model.state_mean.device, model.state_mean.dtype
    x = data.x.to(device=device, dtype=dtype)
    t = data.t.to(device=device, dtype=dtype)
    parts = []
    with torch.no_grad():
        for start in range(0, x.shape[0], batch_size):
            sl = slice(start, start + batch_size)
            ei = data.edge_index if data.shared_graph else data.edge_index[sl]
            u = None if data.u is None else data.u[sl].to(x)
            nf = data.node_features
            if nf is not None and nf.dim() == 3:
                nf = nf[sl]
            try:
                parts.append(one_step(model, x[sl], t, Inputs(ei.to(device), u, nf, data.meta)))
            except DivergenceError:
                parts.append(torch.full_like(x[sl, 1:], float("nan")))
    pred = torch.cat(parts).double().cpu()  # [B, T-1, N, D]
    dt = (data.t[1:] - data.t[:-1]).double()
    r = (data.x[:, 1:].double() - pred) / dt[None, :, None, None]
    return Residual(r=r, pred=pred, t_mid=0.5 * (data.t[1:] + data.t[:-1]).double(), dt=dt)
