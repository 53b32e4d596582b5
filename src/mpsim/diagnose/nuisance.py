"""The directions a model explains itself, refit beside every candidate but never named.

The screen regresses the one-step residual on candidate columns with these *nuisance* columns projected out: the
model's sensitivities to its own interpretable parameters, the basis of each effect it already carries, and the
columns of every effect kind (and state polynomial) it can express by itself.
"""

from __future__ import annotations

import inspect
from typing import Any, cast

import torch

from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.library import Candidate, build_library, delayed, evaluate_effect
from mpsim.diagnose.residual import Residual
from mpsim.diagnose.select import project_out
from mpsim.models.base import Model
from mpsim.models.capabilities import ExpressesEffects, Interpretable
from mpsim.polynomials import monomial_features
from mpsim.signals import input_hold


def project(y: torch.Tensor, groups: list[torch.Tensor], base: torch.Tensor | None):
    """Residual and candidate columns with the nuisance (base) directions projected out, in their shapes."""
    if base is None:
        return y, groups
    n = y.numel()
    flat = project_out(base.reshape(n, -1), y.reshape(n), *[g.reshape(n, -1) for g in groups])
    return flat[0].reshape(y.shape), [f.reshape(g.shape) for f, g in zip(flat[1:], groups, strict=True)]


def target_rows(library: list[Candidate], res: Residual, d: int, keep: torch.Tensor, base: torch.Tensor | None):
    """Residual of state d, the candidates' columns and the model's own sensitivity columns for state d,
    per trajectory (finite trajectories only)."""
    y = res.r[keep, :, :, d]  # [B', T-1, N]
    groups = [c.row(d)[keep] for c in library]  # each [B', T-1, N, K]
    return y, groups, None if base is None else base[keep][..., d, :]  # [B', T-1, N, P]


@torch.no_grad()
def model_sensitivities(model: Model, data: Trajectories, by_time: bool = False) -> torch.Tensor | None:
    """[B, T−1, N, D, P] step-averaged sensitivities of the model's field to its own parameters (or None);
    with `by_time` each sample's times its time t (the data's own clock), before the step average.

    With inputs (a driven white-box model) each sample's sensitivity is taken with its own input; under a
    zero-order hold (`meta["input_hold"] = "zoh"`) step k's input is u_k at both of its ends."""
    if not isinstance(model, Interpretable):
        return None
    b, n_t, n, d = data.x.shape
    device, dtype = model.state_mean.device, model.state_mean.dtype
    u_all = data.u if "u" in inspect.signature(model.sensitivities).parameters else None  # models that read inputs

    def at(x: torch.Tensor, t: torch.Tensor, u: torch.Tensor | None) -> torch.Tensor | None:  # x: [B, T', N, D]
        m = x.shape[0] * x.shape[1]
        flat = x.reshape(m, n, d).to(device=device, dtype=dtype)
        times = t[None, :].expand(b, -1).reshape(m, 1).to(device=device, dtype=dtype)
        extra = {} if u is None else {"u": u.reshape(m, n, -1).to(device=device, dtype=dtype)}
        with torch.enable_grad():
            sens = model.sensitivities(times, flat, data.edge_index, **extra)
        if sens is None:
            return None
        sens = sens.detach().double().cpu().reshape(b, x.shape[1], n, d, -1)
        return sens * t.double().cpu()[None, :, None, None, None] if by_time else sens

    if u_all is not None and input_hold(data.meta) == "zoh":
        start, end = at(data.x[:, :-1], data.t[:-1], u_all[:, :-1]), at(data.x[:, 1:], data.t[1:], u_all[:, :-1])
        return None if start is None or end is None else 0.5 * (start + end)
    sens = at(data.x, data.t, u_all)
    return None if sens is None else 0.5 * (sens[:, 1:] + sens[:, :-1])


@torch.no_grad()
def drift_candidates(model: Model, data: Trajectories, kinds: tuple[str, ...]) -> list[Candidate]:
    """The `ParameterDrift` candidates of a white-box model (`model=equations`): one per learnable scalar
    parameter p that does not drift already, its column on state row d the step average of t·p·∂f_d/∂p — the
    first-order change of the field when p becomes p·(1 + s·t), per unit s (t: the data's own time).

    Fixed parameters are not offered: the spec declares them known, and in a ratio such as k/m the drift of a
    fixed m is the drift of a learnable k. Per-node and matrix parameters are not offered either (one rate each
    would be one candidate per node)."""
    drifts = getattr(model, "drifts", None)
    if "ParameterDrift" not in kinds or drifts is None or not isinstance(model, Interpretable):
        return []
    names = model.sensitivity_names()
    values = cast(Any, model).parameters_now()
    drifting = {cast(Any, e).param for e in drifts()}
    chosen = [i for i, n in enumerate(names) if n in values and values[n].dim() == 0 and n not in drifting]
    if not chosen:
        return []
    sens = model_sensitivities(model, data, by_time=True)  # [B, T-1, N, D, P]
    if sens is None:
        return []
    return [
        Candidate(
            "ParameterDrift",
            None,
            {"param": names[i]},
            float(values[names[i]].detach()) * sens[..., i : i + 1],  # [B, T-1, N, D, 1]
            per_row=True,
        )
        for i in chosen
    ]


@torch.no_grad()
def input_gain_candidates(model: Model, data: Trajectories, kinds: tuple[str, ...]) -> list[Candidate]:
    """The `InputGain` candidates of a driven white-box model (`model=equations`): one per input, on every state
    row, with one column per recording b: the step average of ∂f_d/∂u·u on b's samples (zero on the others) — the
    first-order change of the field when the input reaches the system as (1 + c_b)·u, per unit c_b. Offered with
    two recordings or more (with one it is the input's own coefficient in the equations, no finding); under a
    zero-order hold step k's input is u_k at both of its ends."""
    sens_of = getattr(model, "input_sensitivity", None)
    names = list(getattr(getattr(model, "spec", None), "inputs", ()) or ())
    if "InputGain" not in kinds or sens_of is None or data.u is None or not names or len(data) < 2:
        return []
    b, n_t, n, d = data.x.shape
    device, dtype = model.state_mean.device, model.state_mean.dtype

    def at(x: torch.Tensor, t: torch.Tensor, u: torch.Tensor, c: int) -> torch.Tensor:  # x: [B, T', N, D]
        m = x.shape[0] * x.shape[1]
        times = t[None, :].expand(b, -1).reshape(m, 1).to(device=device, dtype=dtype)
        flat = x.reshape(m, n, d).to(device=device, dtype=dtype)
        with torch.enable_grad():
            col = sens_of(times, flat, data.edge_index, u.reshape(m, n, -1).to(device=device, dtype=dtype), c)
        return col.detach().double().cpu().reshape(b, x.shape[1], n, d)

    out = []
    eye = torch.eye(b, dtype=torch.float64)
    for c, name in enumerate(names):  # the spec's few inputs
        if input_hold(data.meta) == "zoh":
            col = 0.5 * (
                at(data.x[:, :-1], data.t[:-1], data.u[:, :-1], c) + at(data.x[:, 1:], data.t[1:], data.u[:, :-1], c)
            )
        else:
            full = at(data.x, data.t, data.u, c)
            col = 0.5 * (full[:, 1:] + full[:, :-1])  # [B, T-1, N, D]
        if not bool(col.abs().amax() > 0):  # the input enters no row
            continue
        feats = col[..., None] * eye[:, None, None, None, :]  # [B, T-1, N, D, B]: recording b's column is b's own
        out.append(Candidate("InputGain", None, {"input": name}, feats, per_row=True))
    return out


def nuisance_columns(model: Model, data: Trajectories, represented: tuple[str, ...]) -> tuple[torch.Tensor | None, int]:
    """([B, T−1, N, D, P] columns refit but never named, how many of them are the model's own coefficients).

    First the model's own coefficients, one column each across all state variables: its sensitivities to its
    interpretable parameters (white-box models) and the basis of every effect it already carries (placed in
    the rows of the effect's target; in a later round of the loop a drive found before is refit, not found
    again). Then the basis of every effect kind the model can already express (a neural ODE of the node state
    can learn any state-dependent term, so its residual along those directions is training error, not missing
    physics) and the polynomials of a node's state, with a coefficient per state variable.
    """
    parts = []
    sens = model_sensitivities(model, data)
    if sens is not None:
        parts.append(sens)
    own = effect_columns(model, data)
    if own is not None:
        parts.append(own)
    n_shared = sum(p.shape[-1] for p in parts)
    if represented:
        # a represented coupling kind projects out its first harmonic, as before the library had harmonics (its
        # higher ones are not searched either: the kind is left out of the search whole)
        lib = build_library(data, {}, [], represented, harmonics=(1,), one_signed_friction=True)
        cols = torch.cat([c.basis for c in lib], dim=-1)  # [B, T-1, N, K]
        parts.append(cols.unsqueeze(-2).expand(-1, -1, -1, data.state_dim, -1))
    if isinstance(model, ExpressesEffects) and model.represents_polynomials:
        cols = monomial_features(data.x.double(), model.represents_polynomials)  # [B, T, N, K]
        cols = 0.5 * (cols[:, 1:] + cols[:, :-1])
        parts.append(cols.unsqueeze(-2).expand(-1, -1, -1, data.state_dim, -1))
    return (torch.cat(parts, dim=-1) if parts else None), n_shared


@torch.no_grad()
def effect_columns(model: Model, data: Trajectories) -> torch.Tensor | None:
    """[B, T−1, N, D, K] step-averaged basis of each effect the model carries, in its target's rows (or None)."""
    cols = []
    for effect in model.effects:
        effect = cast(Any, effect)  # an Effect (a Module list holds Modules)
        if getattr(effect, "acts_on_parameters", False):  # a carried drift: t·p·∂f/∂p on every row, refit
            cols.append(_carried_drift(model, data, effect.param))
            continue
        if type(effect).__name__ == "DelayedFeedback":
            m = int(round(float(effect.delay) / float(data.t[1] - data.t[0])))
            values = delayed(data.x.double(), m)[..., effect.source : effect.source + 1]
        else:
            values = evaluate_effect(effect, data)
        feats = 0.5 * (values[:, 1:] + values[:, :-1])  # [B, T-1, N, K]
        full = feats.new_zeros(*feats.shape[:-1], data.state_dim, feats.shape[-1])
        full[..., effect.target, :] = feats
        cols.append(full)
    return torch.cat(cols, dim=-1) if cols else None


def _carried_drift(model: Model, data: Trajectories, param: str) -> torch.Tensor:
    """[B, T−1, N, D, 1] the column of a drift the model carries: t·p·∂f/∂p (zeros where p has no sensitivity)."""
    names = model.sensitivity_names() if isinstance(model, Interpretable) else []
    b, n_t, n, d = data.x.shape
    if param not in names:
        return torch.zeros(b, n_t - 1, n, d, 1, dtype=torch.float64)
    sens = model_sensitivities(model, data, by_time=True)
    assert sens is not None  # an Interpretable model with a named parameter has its sensitivity
    i = names.index(param)
    return float(cast(Any, model).parameters_now()[param].detach()) * sens[..., i : i + 1]
