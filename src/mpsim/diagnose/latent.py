"""Unmeasured states in multi-step prediction: each window's latent start, fitted.

Data with unmeasured states (`Trajectories.latent_index`, e.g. a velocity when only positions are measured;
`data.observed`) hold a first estimate of them (`mpsim.data.latent`: a smoothed derivative). A window that
started from that estimate would carry its error through the window, so the latent components of every
window's start are free values, started from the estimate and fitted to the window's *measured* states:

- **Held-in windows, in a multiple-shooting fit** (`shooting.shooting_fit`): jointly with the model's
  parameters, by variable projection — at every evaluation of the fit's objective each window's latent start is
  the best one for the current parameters (`fit_latent`), and the gradient with respect to the parameters taken
  at those starts is the gradient of the joint minimum (envelope theorem). Standard errors project the starts'
  directions out of each window's Jacobian (`profile_out`), so the parameters' intervals include what the free
  starts can absorb.
- **Held-out windows** (`shooting.window_error`) and the held-out rollouts of the loop's report: the latent start
  fitted on the window's own measured samples with the model fixed — state estimation, not parameter fitting: the
  model given, refit or with a candidate, and its null data, are all scored this way.

`fit_latent` is Levenberg–Marquardt, batched over every window of every trajectory at once: windows are
independent given their starts, so a central difference of all windows' starts along one latent column
(one per node and latent state: a handful) gives every window's Jacobian in two rollouts, and the small normal
equations are solved as one batch. Starts are kept in normalised units (the model's `state_std`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.windows import window_residuals, window_starts
from mpsim.errors import DivergenceError
from mpsim.models.base import Model

#: Levenberg–Marquardt iterations of a state estimation from the data's estimate, and of each refresh inside a fit
#: (warm-started from the last evaluation; the starts enter the measured states nearly linearly)
LATENT_ITERS, REFRESH_ITERS = 6, 1
#: difference step of the latent starts (normalised units): far above an adaptive solver's tolerance
FD_STEP = 1e-3
#: a state estimation stops when no window's start moves more than this (normalised units), or when no window's
#: next step is predicted to lower its squared error by more than this share (the starts enter nearly linearly:
#: one Gauss–Newton step usually lands, and the rest would cost a rollout each for nothing)
STEP_TOL, COST_TOL = 1e-6, 1e-4


@dataclass(frozen=True)
class LatentStarts:
    """The latent components of every window's start, for one set of records and window length.

    Attributes:
        z: [B, K, N, L] normalised latent starts (K windows, L latent states).
        index: the latent state columns (`Trajectories.latent_index`).
        length: the window length (steps) the windows were made with.
    """

    z: torch.Tensor
    index: list[int]
    length: int

    def states(self, model: Model, data: Trajectories) -> torch.Tensor:
        """[B, K, N, D] every window's initial state: the data's measured states at its first step, the latent
        ones from `z` (raw units)."""
        dtype = model.state_mean.dtype
        x0 = data.x[:, window_starts(data.n_times, self.length)].to(model.state_mean.device, dtype).clone()
        mean, std = model.state_mean[self.index], model.state_std[self.index]
        x0[..., self.index] = mean + std * self.z.to(x0)
        return x0

    def raw(self, model: Model) -> torch.Tensor:
        """[B, K, N, L] the latent starts in raw units."""
        return (model.state_mean[self.index] + model.state_std[self.index] * self.z.to(model.state_mean)).detach()


def initial_latent(model: Model, data: Trajectories, length: int) -> LatentStarts | None:
    """The latent starts as the data estimate them (None when every state is measured)."""
    index = data.latent_index
    if not index:
        return None
    x0 = data.x[:, window_starts(data.n_times, length)][..., index].to(model.state_mean)  # [B, K, N, L]
    z = (x0 - model.state_mean[index]) / model.state_std[index]
    return LatentStarts(z.detach(), index, length)


def fitted_latent(model: Model, data: Trajectories, length: int, iters: int = LATENT_ITERS) -> LatentStarts | None:
    """The latent starts fitted with the model fixed (state estimation), from the data's estimate; None when
    every state is measured."""
    latent = initial_latent(model, data, length)
    return None if latent is None else fit_latent(model, data, latent, iters)


def _residuals(
    model: Model,
    data: Trajectories,
    latent: LatentStarts,
    zs: torch.Tensor,  # [S, B, K, N, L] S sets of normalised latent starts
) -> torch.Tensor:
    """[S, B, K, M] flattened window residuals at S sets of latent starts `zs` [S, B, K, N, L], all in one batched
    rollout (the records repeated S times: an adaptive solver's steps cost the same for a batch of S·B), or one
    rollout per set when an effect reads the records' place in the batch (`Effect.per_record`); inf everywhere when
    a rollout failed."""
    n_sets, b = zs.shape[:2]
    try:
        if any(getattr(e, "per_record", False) for e in getattr(model, "effects", ())):  # read the batch order
            parts = [
                window_residuals(model, data, latent.length, replace(latent, z=z).states(model, data))[0] for z in zs
            ]
            res = torch.cat(parts)  # the few sets one after another, each batch in the records' own order
        else:
            tiled = data.subset(torch.arange(b).repeat(n_sets))
            starts = replace(latent, z=zs.flatten(0, 1)).states(model, tiled)
            res, _ = window_residuals(model, tiled, latent.length, starts)
    except DivergenceError:
        return torch.full((*zs.shape[:3], 1), torch.inf, dtype=zs.dtype)
    r = res.flatten(2).to(zs).reshape(n_sets, b, *res.shape[1:2], -1)
    return torch.where(torch.isfinite(r), r, torch.full_like(r, torch.inf))


def _directions(z: torch.Tensor) -> torch.Tensor:  # z: [B, K, N, L] -> [P, B, K, N, L]
    """`FD_STEP` along each of the P = N·L latent columns, for every window at once."""
    eye = torch.eye(z[0, 0].numel(), dtype=z.dtype) * FD_STEP  # [P, P]
    return eye.reshape(-1, 1, 1, *z.shape[2:]).expand(-1, *z.shape)


def _linearise(
    model: Model,
    data: Trajectories,
    latent: LatentStarts,
    z: torch.Tensor,  # [B, K, N, L] normalised latent starts
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """([B, K, M] residuals, [B, K, M, P] forward-difference Jacobian, [B, K] cost) at the starts `z`, from one
    rollout of the records at z and at z moved along each latent column."""
    r = _residuals(model, data, latent, torch.cat([z[None], z[None] + _directions(z)]))
    if r.shape[-1] == 1 and not torch.isfinite(r).all():  # the rollout failed
        inf = torch.full(z.shape[:2], torch.inf, dtype=z.dtype)
        return r[0], r[1:].permute(1, 2, 3, 0), inf
    jac = ((r[1:] - r[:1]) / FD_STEP).permute(1, 2, 3, 0)
    cost = r[0].pow(2).sum(-1)
    return r[0], jac, torch.where(torch.isfinite(cost), cost, torch.full_like(cost, torch.inf))


@torch.no_grad()
def latent_jacobian(model: Model, data: Trajectories, latent: LatentStarts) -> torch.Tensor:
    """[B, K, M, P] each window's Jacobian of its flattened residuals with respect to its own latent start
    (P = N·L columns), by central differences of every window at once (one batched rollout)."""
    step = _directions(latent.z)
    r = _residuals(model, data, latent, torch.cat([latent.z[None] + step, latent.z[None] - step]))
    plus, minus = r.chunk(2)
    return ((plus - minus) / (2 * FD_STEP)).permute(1, 2, 3, 0)


@torch.no_grad()
def fit_latent(model: Model, data: Trajectories, latent: LatentStarts, iters: int = LATENT_ITERS) -> LatentStarts:
    """`latent` refined by up to `iters` Levenberg–Marquardt steps on every window's measured residuals, the model
    fixed; a window keeps its start where a step does not lower its error. One batched rollout per step."""
    z = latent.z.clone()
    r, jac, cost = _linearise(model, data, latent, z)
    damping = torch.full(cost.shape, 1e-3, dtype=z.dtype)  # [B, K]
    for _ in range(iters):  # iterations of one batched solve over every window
        if not (torch.isfinite(jac).all() and torch.isfinite(r).all()):
            break
        a = jac.mT @ jac  # [B, K, P, P]
        g = (jac.mT @ r[..., None])[..., 0]  # [B, K, P]
        scale = torch.diag_embed(a.diagonal(dim1=-2, dim2=-1).clamp_min(1e-12))
        step = -torch.linalg.solve(a + damping[..., None, None] * scale, g[..., None])[..., 0]  # [B, K, P]
        # the decrease the linearisation predicts: −(2 gᵀs + sᵀ A s)
        predicted = -(2 * (g * step).sum(-1) + (step[..., None, :] @ a @ step[..., None])[..., 0, 0])
        step = step.reshape(z.shape)
        if float(step.abs().max()) < STEP_TOL or bool((predicted <= COST_TOL * cost + 1e-30).all()):
            break
        r_new, jac_new, cost_new = _linearise(model, data, latent, z + step)
        better = cost_new < cost  # [B, K]
        z = torch.where(better[..., None, None], z + step, z)
        if r_new.shape == r.shape:
            r = torch.where(better[..., None], r_new, r)
            jac = torch.where(better[..., None, None], jac_new, jac)
        cost = torch.where(better, cost_new, cost)
        damping = torch.where(better, damping * 0.3, damping * 10.0)
    return replace(latent, z=z)


def profile_out(
    jac: torch.Tensor,  # [B, K, M, P'] Jacobian of every window's residuals with respect to the model's parameters
    jac_latent: torch.Tensor,  # [B, K, M, P] ... with respect to the window's own latent start
) -> torch.Tensor:
    """[B, K, M, P'] `jac` with each window's latent-start directions projected out: the Jacobian of the residuals
    at the best latent starts for each parameter value (Gauss–Newton), so parameter intervals count what the
    free starts absorb."""
    coef = torch.linalg.pinv(jac_latent) @ jac  # [B, K, P, P']
    return jac - jac_latent @ coef
