"""The one-step screen: residual → candidate library → sparse selection → bootstrap → null check.

`find_effects` works from trajectories alone: nothing in the data says which effects it contains. An effect
is named only when (1) forward selection with BIC picks it, (2) the share of the residual it explains is
above both an absolute floor and what any candidate explains on a *null* dataset — data simulated from the
fitted model itself plus measurement noise of the level estimated from the data, run through the same
pipeline — and (3) a bootstrap over trajectories selects it in most resamples with a coefficient interval
that excludes zero. Otherwise the answer is "no effect found", with the numbers that say why.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from typing import Any, cast

import torch

from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.library import (
    DEFAULT_KINDS,
    Candidate,
    build_library,
    delayed,
    dominant_frequency,
    evaluate_effect,
    incoherent_frequency,
    refine_frequency,
)
from mpsim.diagnose.noise import noise_level
from mpsim.diagnose.residual import Residual, one_step_residual
from mpsim.diagnose.select import bootstrap, explained_alone, lstsq, project_out, stepwise_bic
from mpsim.diagnose.shooting import window_predictions
from mpsim.errors import DivergenceError
from mpsim.models.base import Model
from mpsim.models.capabilities import ExpressesEffects, Interpretable
from mpsim.polynomials import monomial_features
from mpsim.training.trainer import predict


@dataclass
class Finding:
    """One candidate selected for one state variable, with the evidence for and against it."""

    target: int
    label: str
    kind: str
    coef: list[float]
    interval: list[tuple[float, float]]
    gain: float  # share of the residual sum of squares it removed on entry
    explained_rms: float  # the part of the residual it accounts for, in the residual's units (RMS)
    alone: float  # share it explains on its own
    inclusion: float  # bootstrap inclusion frequency
    threshold: float  # the explained RMS it had to reach (null_factor × what any candidate explains on null data)
    accepted: bool
    reason: str
    effect: dict[str, Any]  # Hydra config of the effect with the fitted coefficients

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass
class Diagnosis:
    """Everything `find_effects` measured (plain data for diagnosis.json, tensors for the plots)."""

    findings: list[Finding]
    state_names: list[str]
    residual_rms: list[float]  # per state variable, on the data
    null_rms: list[float]  # per state variable, on the null data
    null_level: list[float]  # per state variable: largest RMS any candidate explains on the null data
    explained: dict[str, list[float]]  # candidate label -> share explained alone, per state variable
    omegas: dict[int, float]  # forcing frequency found per state variable
    noise_std: list[float]  # estimated measurement noise per state variable
    residual: Residual | None = None
    periodograms: dict[int, tuple[torch.Tensor, torch.Tensor]] = field(default_factory=dict)
    parameter_shifts: dict[str, float] = field(default_factory=dict)  # refit of the model's own parameters
    represented: list[str] = field(default_factory=list)  # effect kinds the model can express itself
    not_considered: list[str] = field(default_factory=list)  # kinds that cannot be told apart from model error
    searched: list[str] = field(default_factory=list)  # state rows searched (the dynamic rows by default)
    phased_omegas: dict[int, float] = field(default_factory=dict)  # drive frequencies with a phase per recording

    @property
    def accepted(self) -> list[Finding]:
        return [f for f in self.findings if f.accepted]

    def as_dict(self) -> dict[str, Any]:
        return {
            "effects_found": [f.as_dict() for f in self.accepted],
            "candidates_considered": [f.as_dict() for f in self.findings],
            "state_names": self.state_names,
            "residual_rms": self.residual_rms,
            "null_rms": self.null_rms,
            "null_level": self.null_level,
            "explained_alone": self.explained,
            "forcing_omegas": {self.state_names[k]: v for k, v in self.omegas.items()},
            "noise_std_estimate": self.noise_std,
            "parameter_shifts": self.parameter_shifts,
            "represented_by_model": self.represented,
            "not_considered": self.not_considered,
            "searched_rows": self.searched,
        }


def _forcing_omegas(res: Residual, data: Trajectories) -> tuple[dict[int, float], dict[int, tuple]]:
    """The dominant residual frequency of each state variable. Frequencies of different variables closer than
    a quarter of the record's frequency bin are one drive seen twice (a drive on x leaks into y within a step):
    they are merged into the one with the stronger peak, since two near-equal sinusoids are collinear."""
    omegas, spectra, peaks = {}, {}, {}
    span = 2 * math.pi / float(data.t[-1] - data.t[0])  # one frequency bin of the record length
    finite = torch.isfinite(res.r).flatten(1).all(dim=1)
    for d in range(data.state_dim):
        r = res.r[finite, :, :, d]
        omega0, freqs, power = dominant_frequency(r, res.t_mid)
        signal = r.mean(dim=(0, 2))
        omegas[d] = refine_frequency(signal, res.t_mid, omega0, span)
        spectra[d] = (freqs, power)
        peaks[d] = float(power.max()) if power.numel() else 0.0
    kept: list[float] = []
    for d in sorted(omegas, key=lambda k: peaks[k], reverse=True):
        near = [w for w in kept if abs(w - omegas[d]) < 0.25 * span]
        if near:
            omegas[d] = near[0]
        else:
            kept.append(omegas[d])
    return omegas, spectra


def _phased_omegas(res: Residual, data: Trajectories, targets: list[int] | None) -> dict[int, float]:
    """Per searched state variable, the frequency of a drive whose phase may differ between recordings."""
    finite = torch.isfinite(res.r).flatten(1).all(dim=1)
    rows = range(data.state_dim) if targets is None else targets
    if int(finite.sum()) < 2:
        return {}
    return {d: incoherent_frequency(res.r[finite, :, :, d], res.t_mid) for d in rows}


def _project(y: torch.Tensor, groups: list[torch.Tensor], base: torch.Tensor | None):
    """Residual and candidate columns with the nuisance (base) directions projected out, in their shapes."""
    if base is None:
        return y, groups
    n = y.numel()
    flat = project_out(base.reshape(n, -1), y.reshape(n), *[g.reshape(n, -1) for g in groups])
    return flat[0].reshape(y.shape), [f.reshape(g.shape) for f, g in zip(flat[1:], groups, strict=True)]


#: groups rerun in each bootstrap resample: the selected ones plus this many of the strongest others
BOOT_GROUPS = 8


def _fit_target(
    y: torch.Tensor,
    groups: list[torch.Tensor],
    base: torch.Tensor | None,
    n_boot: int,
    seed: int,
    same: list[int] | None = None,
):
    """Selection, explained shares and bootstrap on the residual left after the nuisance fit (the bootstrap
    resamples trajectories of the projected data: the nuisance fit itself is not redone per resample)."""
    y, groups = _project(y, groups, base)
    b = y.shape[0]
    flat_y = y.reshape(-1)
    flat_g = [g.reshape(flat_y.numel(), -1) for g in groups]
    sel = stepwise_bic(flat_y, flat_g)
    if base is not None:  # the nuisance columns count as parameters of every model in the BIC
        sel.bic_path = [v + base.shape[-1] * math.log(flat_y.numel()) for v in sel.bic_path]
    alone = explained_alone(flat_y, flat_g)
    # the bootstrap reruns the selection among the selected groups and the strongest others (a group that
    # explains little alone and was not selected is not selected in resamples either)
    keep = sorted(set(sel.groups) | set(sorted(range(len(groups)), key=lambda g: -alone[g])[:BOOT_GROUPS]))
    sub_freq, sub_int = bootstrap(
        y.reshape(b, -1),
        [groups[g].reshape(b, -1, groups[g].shape[-1]) for g in keep],
        [keep.index(g) for g in sel.groups],
        n_boot,
        seed,
        same=None if same is None else [same[g] for g in keep],
    )
    freq = {g: 0.0 for g in range(len(groups))} | {keep[i]: v for i, v in sub_freq.items()}
    intervals = {keep[i]: v for i, v in sub_int.items()}
    return sel, alone, freq, intervals


def _rows(library: list[Candidate], res: Residual, d: int, keep: torch.Tensor, base: torch.Tensor | None):
    """Residual of state d, the candidates' columns and the model's own sensitivity columns for state d,
    per trajectory (finite trajectories only)."""
    y = res.r[keep, :, :, d]  # [B', T-1, N]
    groups = [c.basis[keep] for c in library]  # each [B', T-1, N, K]
    return y, groups, None if base is None else base[keep][..., d, :]  # [B', T-1, N, P]


@torch.no_grad()
def model_sensitivities(model: Model, data: Trajectories) -> torch.Tensor | None:
    """[B, T−1, N, D, P] step-averaged sensitivities of the model's field to its own parameters (or None)."""
    if not isinstance(model, Interpretable):
        return None
    b, n_t, n, d = data.x.shape
    device, dtype = model.state_mean.device, model.state_mean.dtype
    flat = data.x.reshape(b * n_t, n, d).to(device=device, dtype=dtype)
    t = data.t[None, :].expand(b, n_t).reshape(b * n_t, 1).to(device=device, dtype=dtype)
    with torch.enable_grad():
        sens = model.sensitivities(t, flat, data.edge_index)
    if sens is None:
        return None
    sens = sens.detach().double().cpu().reshape(b, n_t, n, d, -1)
    return 0.5 * (sens[:, 1:] + sens[:, :-1])


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
        cols = torch.cat([c.basis for c in build_library(data, {}, [], represented)], dim=-1)  # [B, T-1, N, K]
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


def find_effects(
    model: Model,
    data: Trajectories,
    kinds: tuple[str, ...] = DEFAULT_KINDS,
    delays: list[float] | None = None,
    n_boot: int = 100,
    min_gain: float = 0.05,
    null_factor: float = 3.0,
    min_inclusion: float = 0.8,
    seed: int = 0,
    targets: list[int] | None = None,
    null_segment: int | None = None,
) -> Diagnosis:
    """Trace the residual of `model` on `data` (held-in trajectories) to named effects.

    Args:
        model: the trained model (any `Model` that steps from one state).
        data: trajectories the model was trained on (or other held-in data).
        kinds: effect classes to consider (default: all of `mpsim.effects`).
        delays: delays of the delayed-feedback candidates (default: 1, 2, 4 and 8 sampling steps).
        n_boot: bootstrap resamples over trajectories.
        min_gain: smallest share of the residual an effect must explain to be named.
        null_factor: the part of the residual an effect explains (RMS, absolute units) must be this many times
            the largest part any candidate explains on the null data.
        min_inclusion: smallest bootstrap inclusion frequency.
        seed: seed of the bootstrap and of the null data's noise.
        targets: state rows searched for effects (default: all; `dynamic_rows` leaves out kinematic ones).
        null_segment: steps the model tracks the data (a chaotic system): the null data are then simulated window
            by window from observed states, as the held-out judgement's are (None: whole records).
    """
    dt = float(data.t[1] - data.t[0])
    delays = [m * dt for m in (1, 2, 4, 8)] if delays is None else delays
    res = one_step_residual(model, data)
    keep = torch.isfinite(res.r).flatten(1).all(dim=1)
    omegas, spectra = _forcing_omegas(res, data) if "PeriodicForcing" in kinds else ({}, {})
    phased = _phased_omegas(res, data, targets) if "PeriodicForcing" in kinds else {}
    expressed, undecided = (
        (model.represents, model.indistinguishable) if isinstance(model, ExpressesEffects) else ((), ())
    )
    represented = tuple(k for k in kinds if k in expressed)
    undecidable = tuple(k for k in kinds if k in undecided)
    kinds = tuple(k for k in kinds if k not in represented and k not in undecidable)
    library = build_library(data, omegas, delays, kinds, phased)
    base, n_shared = nuisance_columns(model, data, represented)
    noise = noise_level(data.x, res.r * res.dt[None, :, None, None])
    null_rms, null_level = _null_check(
        model, data, omegas, delays, kinds, represented, noise, seed, phased, null_segment
    )
    names = data.state_names
    findings: list[Finding] = []
    explained: dict[str, list[float]] = {c.label(names): [0.0] * data.state_dim for c in library}
    residual_rms = []
    searched = list(range(data.state_dim)) if targets is None else list(targets)
    for d in range(data.state_dim):
        y, groups, base_d = _rows(library, res, d, keep, base)
        if d not in searched:  # a kinematic row (θ̇ = ω): its residual is reported, never searched
            flat = _project(y, groups, base_d)[0].reshape(-1)
            residual_rms.append(math.sqrt(float(flat.pow(2).sum()) / max(flat.numel(), 1)))
            continue
        sel, alone, freq, intervals = _fit_target(y, groups, base_d, n_boot, seed, _drive_twins(library))
        residual_rms.append(math.sqrt(sel.total / max(y.numel(), 1)))
        for g, c in enumerate(library):
            explained[c.label(names)][d] = alone[g]
        threshold = null_factor * null_level[d]
        for g in sel.groups:
            c = library[g]
            ci = intervals.get(g, [])
            excludes_zero = any(lo > 0 or hi < 0 for lo, hi in ci)
            part = residual_rms[d] * math.sqrt(sel.gains[g])
            checks = [
                (sel.gains[g] >= min_gain, f"explains {sel.gains[g]:.1%} of the residual, below {min_gain:.0%}"),
                (
                    part >= threshold,
                    f"accounts for an RMS of {part:.3g}, below {null_factor:g}× the null level "
                    f"({threshold:.3g}): indistinguishable from noise and discretisation error",
                ),
                (freq[g] >= min_inclusion, f"selected in only {freq[g]:.0%} of bootstrap resamples"),
                (excludes_zero, "its bootstrap interval includes zero"),
            ]
            failed = [why for ok, why in checks if not ok]
            findings.append(
                Finding(
                    target=d,
                    label=c.label(names, d),
                    kind=c.kind,
                    coef=sel.coef[g],
                    interval=ci,
                    gain=sel.gains[g],
                    explained_rms=part,
                    alone=alone[g],
                    inclusion=freq[g],
                    threshold=threshold,
                    accepted=not failed,
                    reason="; ".join(failed) if failed else "selected, above the null level, stable under bootstrap",
                    effect=c.effect_config(sel.coef[g], d, names),
                )
            )
    diag = Diagnosis(
        findings,
        list(names),
        residual_rms,
        null_rms,
        null_level,
        explained,
        omegas,
        [float(v) for v in noise],
        res,
        spectra,
        represented=list(represented),
        not_considered=list(undecidable),
        searched=[names[d] for d in searched],
        phased_omegas=phased,
    )
    while diag.accepted and not _joint_refit(diag, library, res, keep, base, n_shared, model):
        pass  # an effect whose coefficient was not stable was dropped: refit the others
    while diag.accepted and not _confirm_by_integration(diag, library, model, data, base, min_gain):
        while diag.accepted and not _joint_refit(diag, library, res, keep, base, n_shared, model):
            pass
    return diag


def _fit_one(cand: Candidate, res: Residual, target: int, keep: torch.Tensor, base: torch.Tensor | None):
    """Least-squares fit of one candidate to one variable's residual (nuisance projected out): the coefficient
    vector, the share of the residual it explains and the RMS it accounts for."""
    y, groups, base_d = _rows([cand], res, target, keep, base)
    y, (g,) = _project(y, groups, base_d)
    flat_y, flat_g = y.reshape(-1), g.reshape(y.numel(), -1)
    sol, _ = lstsq(flat_g, flat_y)
    fitted = float((flat_g @ sol).pow(2).sum())
    return sol, fitted / max(float(flat_y.pow(2).sum()), 1e-300), math.sqrt(fitted / max(flat_y.numel(), 1))


def _confirm_by_integration(
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
            delta, _, _ = _fit_one(cand, res, strong.target, keep, base)
            coef = [c + float(d) for c, d in zip(coef, delta, strict=True)]
            trial.effects[-1] = cand.make_effect(coef, strong.target, names).to(dtype)
            if float(delta.norm()) <= 1e-3 * math.hypot(*coef):
                break
        strong.coef, strong.effect = coef, cand.effect_config(coef, strong.target, names)
        if i == len(order) - 1:
            break
        res = one_step_residual(trial, data)
        keep = torch.isfinite(res.r).flatten(1).all(dim=1)
        for f in order[i + 1 :]:
            sol, gain, part = _fit_one(library[labels[f.label.split(": ", 1)[1]]], res, f.target, keep, base)
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


def _joint_refit(
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
        cols = library[labels[f.label.split(": ", 1)[1]]].basis[keep].reshape(n, -1)
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
    if base is not None and names:
        diag.parameter_shifts = {name: float(v) for name, v in zip(names, sol[at : at + len(names)], strict=True)}
    return True


def _null_check(model, data, omegas, delays, kinds, represented, sigma, seed, phased=None, segment=None):
    """Run the pipeline on data simulated from the model itself plus the estimated measurement noise.

    With `segment` shorter than the records (a chaotic system) the simulation restarts from the observed state
    every `segment` steps, so that it stays on the data's attractor (a whole-record simulation of a chaotic
    model leaves it, and its residual there says nothing about the data); the steps that end on a restart are a
    jump, not the model's step, and are left out of every fit.

    Returns:
        ([D] residual RMS on the null data (after the base fit), [D] the largest RMS any candidate explains there).
    """
    pred, jumps = _null_simulation(model, data, segment)
    gen = torch.Generator().manual_seed(seed + 1)
    noise = torch.randn(pred.shape, generator=gen, dtype=torch.float64) * sigma
    null = Trajectories(
        t=data.t,
        x=(pred.double() + noise).nan_to_num(),
        edge_index=data.edge_index,
        u=data.u,
        node_features=data.node_features,
        meta=data.meta,
    )
    res = one_step_residual(model, null)
    keep = torch.isfinite(res.r).flatten(1).all(dim=1)
    library = build_library(null, omegas, delays, kinds, phased)
    base, _ = nuisance_columns(model, null, represented)
    if jumps:  # a zero row (residual and columns) drops out of every least-squares fit
        res.r[:, jumps] = 0.0
        for c in library:
            c.basis[:, jumps] = 0.0
        if base is not None:
            base[:, jumps] = 0.0
    used = 1.0 - len(jumps) / max(res.r.shape[1], 1)  # share of the rows that are the model's steps
    rms, level = [], []
    for d in range(data.state_dim):
        y, groups, base_d = _rows(library, res, d, keep, base)
        y, groups = _project(y, groups, base_d)
        flat = y.reshape(-1)
        left = math.sqrt(float(flat.pow(2).sum()) / max(flat.numel() * used, 1))
        rms.append(left)
        alone = explained_alone(flat, [g.reshape(flat.numel(), -1) for g in groups])
        level.append(left * math.sqrt(max(max(alone, default=0.0), 0.0)))
    return rms, level


def _null_simulation(model: Model, data: Trajectories, segment: int | None) -> tuple[torch.Tensor, list[int]]:
    """([B, T, N, D] the model's own simulation of `data`, [steps that end on a restart from an observed state])."""
    if segment is not None and segment < data.n_times - 1:
        try:
            with torch.no_grad():
                windows = window_predictions(model, data, segment)
        except DivergenceError:
            windows = []
        if windows:
            pred = data.x.double().clone()
            for s, p in windows:  # in time order: a window's first sample (observed) overwrites the previous end
                pred[:, s : s + p.shape[1]] = p.detach().double().cpu()
            return pred, [s - 1 for s, _ in windows[1:]]
    pred, _ = predict(model, data)
    return pred, []


def _drive_twins(library: list[Candidate]) -> list[int]:
    """Per candidate, a label shared by a drive with a phase per recording and the shared-phase drive at nearly
    the same frequency (within 2 %): one effect written two ways, for the bootstrap's inclusion count."""
    labels = list(range(len(library)))
    for i, c in enumerate(library):
        if c.kind != "PeriodicForcing" or not c.params.get("phased"):
            continue
        for j, other in enumerate(library):
            if other.kind == "PeriodicForcing" and not other.params.get("phased"):
                if abs(other.params["omega"] - c.params["omega"]) <= 0.02 * c.params["omega"]:
                    labels[i] = labels[j]
    return labels
