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


#: quantiles of |u| over the data where the input-path candidates put their threshold: a dead zone's width (the
#: screen picks the best, the held-out fit moves it continuously) and a saturation's limit (≥ 3 % of the samples
#: beyond it, so the data show it)
DEAD_ZONE_QUANTILES = (0.05, 0.1, 0.2, 0.35)
SATURATION_QUANTILES = (0.97, 0.9, 0.8)
INPUT_KINDS = ("InputGain", "DeadZone", "InputSaturation")


@torch.no_grad()
def input_candidates(model: Model, data: Trajectories, kinds: tuple[str, ...]) -> list[Candidate]:
    """The input-path candidates of a driven white-box model (`model=equations`), per input u, on every state row,
    each column the step average of ∂f_d/∂u·δu (the first-order change of the field when what reaches the system
    is u + δu; under a zero-order hold step k's input is u_k at both of its ends):

    - `InputGain(u, a gain per recording)`: δu = c_b·u, one column per recording b (zero on the others' samples);
      offered with two recordings or more (with one it is the input's own coefficient in the equations);
    - `DeadZone(u, width=w)`: δu = −clip(u, −w, w), w at the quantiles `DEAD_ZONE_QUANTILES` of |u|;
    - `InputSaturation(u, limit=U)`: δu = clip(u, −U, U) − u, U at the quantiles `SATURATION_QUANTILES` of |u|
      (a limit the data never pass is no finding: it is not offered)."""
    sens_of = getattr(model, "input_sensitivity", None)
    names = list(getattr(getattr(model, "spec", None), "inputs", ()) or ())
    wanted = [k for k in INPUT_KINDS if k in kinds]
    if not wanted or sens_of is None or data.u is None or not names:
        return []
    b, n_t, n, d = data.x.shape
    device, dtype = model.state_mean.device, model.state_mean.dtype
    zoh = input_hold(data.meta) == "zoh"
    given = data.u.double()  # [B, T, N, C]

    def at(x: torch.Tensor, t: torch.Tensor, u: torch.Tensor, du: torch.Tensor) -> torch.Tensor:  # x: [B, T', N, D]
        m = x.shape[0] * x.shape[1]
        times = t[None, :].expand(b, -1).reshape(m, 1).to(device=device, dtype=dtype)
        flat = x.reshape(m, n, d).to(device=device, dtype=dtype)
        uu, dd = (v.reshape(m, n, -1).to(device=device, dtype=dtype) for v in (u, du))
        with torch.enable_grad():
            col = sens_of(times, flat, data.edge_index, uu, dd)
        return col.detach().double().cpu().reshape(b, x.shape[1], n, d)

    def column(c: int, change) -> torch.Tensor:  # change: u_c [B, T', N] -> δu_c: [B, T-1, N, D]
        def direction(u: torch.Tensor) -> torch.Tensor:  # u: [B, T', N, C]
            out = torch.zeros_like(u)
            out[..., c] = change(u[..., c])
            return out

        u = given
        if zoh:
            held = u[:, :-1]
            return 0.5 * (
                at(data.x[:, :-1], data.t[:-1], held, direction(held))
                + at(data.x[:, 1:], data.t[1:], held, direction(held))
            )
        full = at(data.x, data.t, u, direction(u))
        return 0.5 * (full[:, 1:] + full[:, :-1])

    out = []
    for c, name in enumerate(names):  # the spec's few inputs
        size = given[..., c].abs().flatten()
        if "InputGain" in wanted and len(data) >= 2:
            col = column(c, lambda v: v)
            if bool(col.abs().amax() > 0):  # the input enters some row
                eye = torch.eye(b, dtype=torch.float64)
                feats = col[..., None] * eye[:, None, None, None, :]  # [B, T-1, N, D, B]: recording b's own column
                out.append(Candidate("InputGain", None, {"input": name}, feats, per_row=True))
        levels = {
            "DeadZone": ("width", DEAD_ZONE_QUANTILES, lambda v, w: -v.clamp(-w, w)),
            "InputSaturation": ("limit", SATURATION_QUANTILES, lambda v, w: v.clamp(-w, w) - v),
        }
        for kind, (key, quantiles, change) in levels.items():  # the two threshold kinds
            if kind not in wanted:
                continue
            for w in sorted({float(q) for q in torch.quantile(size, torch.tensor(quantiles, dtype=torch.float64))}):
                if not w > 0:
                    continue
                col = column(c, lambda v, w=w, change=change: change(v, w))
                if bool(col.abs().amax() > 0):
                    out.append(Candidate(kind, None, {"input": name, key: w}, col[..., None], per_row=True))
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
        if getattr(effect, "acts_on_inputs", False):  # an input gain or threshold: not linear, kept as fitted
            continue
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
