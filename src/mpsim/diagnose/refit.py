"""After selection: the named effects refit together, and confirmed through the model's integration of a step.

Both checks can drop an effect (its coefficient was not stable with the others named, or it was an echo of a
stronger effect through the integration); each returns False when it dropped one, so that the caller refits the
rest and checks again.
"""

from __future__ import annotations

import copy
import math

import torch

from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.findings import Diagnosis, Finding
from mpsim.diagnose.library import Candidate
from mpsim.diagnose.nuisance import project, target_rows
from mpsim.diagnose.residual import Residual, one_step_residual
from mpsim.diagnose.select import lstsq
from mpsim.models.base import Model
from mpsim.models.capabilities import Interpretable


def fit_one(cand: Candidate, res: Residual, target: int, keep: torch.Tensor, base: torch.Tensor | None):
    """Least-squares fit of one candidate to one variable's residual (nuisance projected out): the coefficient
    vector, the share of the residual it explains and the RMS it accounts for."""
    y, groups, base_d = target_rows([cand], res, target, keep, base)
    y, (g,) = project(y, groups, base_d)
    flat_y, flat_g = y.reshape(-1), g.reshape(y.numel(), -1)
    sol, _ = lstsq(flat_g, flat_y)
    fitted = float((flat_g @ sol).pow(2).sum())
    return sol, fitted / max(float(flat_y.pow(2).sum()), 1e-300), math.sqrt(fitted / max(flat_y.numel(), 1))


def confirm_by_integration(
    diag: Diagnosis,
    library: list[Candidate],
    model: Model,
    data: Trajectories,
    base: torch.Tensor | None,
    min_gain: float,
    iterations: int = 3,
) -> bool:
    """Add the named effects to the model one at a time, strongest first, refitting each through the model's
    integration of a step, and test the others against the residual that is left.

    The regression on step-averaged features sees an effect only through the step's integration, which the
    rest of the dynamics shapes (Lorenz's −σx relaxes a drive on x within a step of 0.05 by ≈ σΔt/2): each
    effect's coefficients are corrected by refitting the residual of the model *with* the effect, a few
    fixed-point steps. An effect on one variable also shows up as a small residual in the variables it feeds
    within a step (damping of ω leaves a residual of order c·Δt/2 in θ): a term whose coefficient halves, or
    which falls below its threshold, once the stronger effects are part of the model was such an echo — it is
    rejected and False is returned (the caller refits the rest and calls again)."""
    labels = {c.label(diag.state_names): i for i, c in enumerate(library)}
    order = sorted(diag.accepted, key=lambda f: f.gain, reverse=True)  # share of its own row's residual
    trial = copy.deepcopy(model)
    if isinstance(trial, Interpretable):
        trial.shift_parameters(diag.parameter_shifts)  # the joint refit's correction of the model's own parameters
    dtype = model.state_mean.dtype
    names = diag.state_names
    for i, strong in enumerate(order):
        cand = library[labels[strong.label.split(": ", 1)[1]]]
        coef = list(strong.coef)
        trial.effects.append(cand.make_effect(coef, strong.target, names).to(dtype))
        for _ in range(iterations):
            res = one_step_residual(trial, data)
            keep = torch.isfinite(res.r).flatten(1).all(dim=1)
            if not bool(keep.any()):  # its failure is its own: the rest are refit and checked without it
                return _step_fails(strong, coef)
            delta, _, _ = fit_one(cand, res, strong.target, keep, base)
            coef = [c + float(d) for c, d in zip(coef, delta, strict=True)]
            trial.effects[-1] = cand.make_effect(coef, strong.target, names).to(dtype)
            if float(delta.norm()) <= 1e-3 * math.hypot(*coef):
                break
        strong.coef, strong.effect = coef, cand.effect_config(coef, strong.target, names)
        if i == len(order) - 1:
            break
        res = one_step_residual(trial, data)
        keep = torch.isfinite(res.r).flatten(1).all(dim=1)
        if not bool(keep.any()):
            return _step_fails(strong, coef)
        for f in order[i + 1 :]:
            sol, gain, part = fit_one(library[labels[f.label.split(": ", 1)[1]]], res, f.target, keep, base)
            before, after = math.hypot(*f.coef), float(sol.norm())
            if part < f.threshold or gain < min_gain or after < 0.5 * before:
                f.accepted = False
                f.reason = (
                    f"an echo of {strong.label} through the integration of a step: with that effect in the "
                    f"model its coefficient falls from {before:.3g} to {after:.3g} and it accounts for an RMS "
                    f"of {part:.3g} ({gain:.1%} of the residual; threshold {f.threshold:.3g})"
                )
                return False
    return True


def _step_fails(finding: Finding, coef: list[float]) -> bool:
    """Reject `finding`, with whose coefficients `coef` the model's one-step integration fails: False (the caller
    refits the rest and checks again, without it)."""
    finding.accepted = False
    finding.reason = (
        f"failed: with its coefficients {', '.join(f'{c:.3g}' for c in coef)} the model's one-step integration "
        "diverges on the held-in records (the ODE solver gives up): not an effect they show"
    )
    return False


def joint_refit(
    diag: Diagnosis,
    library: list[Candidate],
    res: Residual,
    keep: torch.Tensor,
    base: torch.Tensor | None,
    n_shared: int,
    model: Model,
) -> bool:
    """One least-squares fit over all state variables of the accepted effects together with the model's own
    parameter sensitivities (shared across state variables): consistent coefficients and parameter shifts
    to start the finetune from.

    An effect whose coefficient, refit with only the named effects, moves from its interval's centre by more
    than both the interval's width and half its size owed its fit to terms that were not named
    (collinearity): it is dropped and False is returned, so that the caller refits the rest."""
    labels = {c.label(diag.state_names): i for i, c in enumerate(library)}
    d_total = res.r.shape[-1]
    y = res.r[keep].reshape(-1, d_total)  # [n, D]
    n = y.shape[0]
    blocks = []
    for f in diag.accepted:  # each effect acts on one state variable: its columns are zero elsewhere
        cand = library[labels[f.label.split(": ", 1)[1]]]
        if cand.per_row:  # a parameter drift: one coefficient across all state variables, as the parameter
            blocks.append(cand.basis[keep].reshape(n, d_total, -1))
            continue
        cols = cand.basis[keep].reshape(n, -1)
        block = torch.zeros(n, d_total, cols.shape[1], dtype=torch.float64)
        block[:, f.target] = cols
        blocks.append(block)
    if base is not None:
        nuisance = base[keep].reshape(n, d_total, -1)  # [n, D, P_shared + K]
        if n_shared:  # parameters of the model's own equations: one coefficient across all state variables
            blocks.append(nuisance[..., :n_shared])
        state = nuisance[:, 0, n_shared:]  # [n, K] state-function columns: separate coefficients per variable
        if state.shape[1]:
            per = torch.zeros(n, d_total, d_total * state.shape[1], dtype=torch.float64)
            for d in range(d_total):  # a handful of state variables
                per[:, d, d * state.shape[1] : (d + 1) * state.shape[1]] = state
            if n_shared:  # the model's own parameters take what they can explain: the state columns keep only
                # the part orthogonal to them (same column space, so the effects' coefficients are unchanged)
                sens = nuisance[..., :n_shared].reshape(n * d_total, n_shared)
                flat = per.reshape(n * d_total, -1)
                scale = sens.norm(dim=0).clamp(min=1e-300)
                coef = torch.linalg.lstsq(sens / scale, flat, driver="gelsd").solution / scale[:, None]
                per = (flat - sens @ coef).reshape(per.shape)
            blocks.append(per)
    x = torch.cat(blocks, dim=-1).reshape(n * d_total, -1)
    sol, _ = lstsq(x, y.reshape(-1))
    at, refits = 0, []
    for f in diag.accepted:
        k = len(f.coef)
        refits.append((f, [float(v) for v in sol[at : at + k]]))
        at += k
    for f, coef in refits:
        unstable = [
            (a, lo, hi)
            for a, (lo, hi) in zip(coef, f.interval, strict=True)
            if abs(a - (lo + hi) / 2) > max(hi - lo, 0.25 * abs(lo + hi))
        ]
        if unstable:
            a, lo, hi = unstable[0]
            f.accepted = False
            f.reason = (
                f"unstable: refit with the other named effects its coefficient moves to {a:.4g}, far from its "
                f"bootstrap interval [{lo:.4g}, {hi:.4g}] (it was explaining what other terms explain)"
            )
            return False
    for f, coef in refits:
        f.coef = coef
        f.effect = library[labels[f.label.split(": ", 1)[1]]].effect_config(coef, f.target, diag.state_names)
    # the first of the shared columns (then the model's effects, not shifted)
    names = model.sensitivity_names() if isinstance(model, Interpretable) else []
    shifts = sol[at : at + n_shared]
    # the shared columns are the model's own parameters only when there is one per named parameter (a spec with
    # `outputs:` or latent states can hand fewer: its sensitivities are then not reported as shifts)
    if base is not None and names and len(names) == n_shared == len(shifts):
        diag.parameter_shifts = {name: float(v) for name, v in zip(names, shifts, strict=True)}
    return True
