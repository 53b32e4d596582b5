"""The one-step screen: residual → candidate library → sparse selection → bootstrap → null check.

`find_effects` works from trajectories alone: nothing in the data says which effects it contains. An effect
is named only when (1) forward selection with BIC picks it, (2) the share of the residual it explains is
above both an absolute floor and what any candidate explains on a *null* dataset — data simulated from the
fitted model itself plus measurement noise of the level estimated from the data, run through the same
pipeline — and (3) a bootstrap over trajectories selects it in most resamples with a coefficient interval
that excludes zero. Otherwise the answer is "no effect found", with the numbers that say why.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from mpsim.data.measurement import as_measured
from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.findings import Diagnosis, Finding
from mpsim.diagnose.library import (
    DEFAULT_KINDS,
    Candidate,
    build_library,
    dominant_frequency,
    incoherent_frequency,
    refine_frequency,
)
from mpsim.diagnose.noise import noise_level
from mpsim.diagnose.nuisance import (
    drift_candidates,
    input_candidates,
    nuisance_columns,
    project,
    target_rows,
)
from mpsim.diagnose.pernode import per_node_variants
from mpsim.diagnose.refit import confirm_by_integration, joint_refit
from mpsim.diagnose.residual import Residual, one_step_residual
from mpsim.diagnose.select import Selection, bootstrap, explained_alone, fit_alone, stepwise_bic
from mpsim.diagnose.shooting import window_predictions
from mpsim.errors import DivergenceError
from mpsim.models.base import Model
from mpsim.models.capabilities import ExpressesEffects
from mpsim.models.rollout import rollout

#: groups rerun in each bootstrap resample: the selected ones plus this many of the strongest others
BOOT_GROUPS = 8


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


def _fit_target(
    y: torch.Tensor,
    groups: list[torch.Tensor],
    base: torch.Tensor | None,
    n_boot: int,
    seed: int,
    same: list[int] | None = None,
):
    """Selection, explained shares (with each group's coefficients fitted alone) and bootstrap on the residual
    left after the nuisance fit (the bootstrap resamples trajectories of the projected data: the nuisance fit
    itself is not redone per resample)."""
    y, groups = project(y, groups, base)
    b = y.shape[0]
    flat_y = y.reshape(-1)
    flat_g = [g.reshape(flat_y.numel(), -1) for g in groups]
    sel = stepwise_bic(flat_y, flat_g, same=same)
    if base is not None:  # the nuisance columns count as parameters of every model in the BIC
        sel.bic_path = [v + base.shape[-1] * math.log(flat_y.numel()) for v in sel.bic_path]
    alone, alone_coef = fit_alone(flat_y, flat_g)
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
    return sel, alone, alone_coef, freq, intervals


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
    represented, undecidable, kinds = _split_kinds(model, kinds)
    equivalent: list[str] = []  # candidates left out: a simpler kind equals them on these data
    library = build_library(data, omegas, delays, kinds, phased, notes=equivalent)
    library += drift_candidates(model, data, kinds) + input_candidates(model, data, kinds)
    base, n_shared = nuisance_columns(model, data, represented)
    noise = noise_level(data.x, res.r * res.dt[None, :, None, None])
    null_rms, null_level = _null_check(
        model, data, omegas, delays, kinds, represented, noise, seed, phased, null_segment
    )
    names = data.state_names
    searched = list(range(data.state_dim)) if targets is None else list(targets)
    variants, per_node_notes = per_node_variants(library, res, keep, base, searched, names, min_gain)
    library += [v for v, _ in variants]
    bars = _Bars(min_gain, null_factor, min_inclusion)
    rows = _search_rows(data, library, res, keep, base, searched, null_level, bars, n_boot, seed)
    diag = Diagnosis(
        rows.findings,
        list(names),
        rows.residual_rms,
        null_rms,
        null_level,
        rows.explained,
        omegas,
        [float(v) for v in noise],
        res,
        spectra,
        represented=list(represented),
        not_considered=list(undecidable),
        searched=[names[d] for d in searched],
        phased_omegas=phased,
        equivalent_forms=equivalent,
        per_node=[pair for _, pair in variants],
        per_node_notes=per_node_notes,
    )
    _refit_named(diag, library, res, keep, base, n_shared, model, data, min_gain)
    return diag


def _split_kinds(model: Model, kinds: tuple[str, ...]) -> tuple[tuple[str, ...], tuple[str, ...], tuple[str, ...]]:
    """(kinds the model expresses itself, kinds it cannot tell apart from its own error, kinds to search)."""
    expressed, undecided = (
        (model.represents, model.indistinguishable) if isinstance(model, ExpressesEffects) else ((), ())
    )
    represented = tuple(k for k in kinds if k in expressed)
    undecidable = tuple(k for k in kinds if k in undecided)
    return represented, undecidable, tuple(k for k in kinds if k not in represented and k not in undecidable)


@dataclass(frozen=True)
class _Bars:
    """What a selected candidate must clear to be named (the arguments of `find_effects` of the same names)."""

    min_gain: float
    null_factor: float
    min_inclusion: float


@dataclass
class _Rows:
    """The screen's results over all state rows."""

    findings: list[Finding]
    explained: dict[str, list[float]]  # candidate label -> share explained alone, per state variable
    residual_rms: list[float]  # per state variable, after the nuisance fit


def _search_rows(
    data: Trajectories,
    library: list[Candidate],
    res: Residual,
    keep: torch.Tensor,  # [B] finite trajectories
    base: torch.Tensor | None,  # [B, T-1, N, D, P] nuisance columns
    searched: list[int],
    null_level: list[float],
    bars: _Bars,
    n_boot: int,
    seed: int,
) -> _Rows:
    """Selection, bootstrap and the checks of each searched state row; the residual RMS of every row."""
    names = data.state_names
    out = _Rows([], {c.label(names): [0.0] * data.state_dim for c in library}, [])
    twins = _drive_twins(library)
    for d in range(data.state_dim):
        y, groups, base_d = target_rows(library, res, d, keep, base)
        if d not in searched:  # a kinematic row (θ̇ = ω): its residual is reported, never searched
            flat = project(y, groups, base_d)[0].reshape(-1)
            out.residual_rms.append(math.sqrt(float(flat.pow(2).sum()) / max(flat.numel(), 1)))
            continue
        sel, alone, alone_coef, freq, intervals = _fit_target(y, groups, base_d, n_boot, seed, twins)
        out.residual_rms.append(math.sqrt(sel.total / max(y.numel(), 1)))
        for g, c in enumerate(library):
            out.explained[c.label(names)][d] = alone[g]
        threshold = bars.null_factor * null_level[d]
        out.findings += [
            _finding(
                library[g], g, d, names, sel, alone, freq, intervals.get(g, []), out.residual_rms[d], threshold, bars
            )
            for g in sel.groups
        ]
        # the joint fit picks one term among near-collinear ones of different kinds (on data stepped by another
        # integrator a delayed copy of the velocity can beat the damping it imitates): the best of every other
        # kind goes to the held-out judgement too, which decides between kinds
        row = out.residual_rms[d]
        out.findings += [
            _best_of_kind(library[g], d, names, alone[g], alone_coef[g], freq[g], row, threshold, bars.min_gain)
            for g in _best_of_kinds(library, alone, sel.groups)
        ]
    return out


def _best_of_kinds(library: list[Candidate], alone: list[float], selected: list[int]) -> list[int]:
    """Per effect kind without a selected candidate, the candidate of that kind that explains most alone (none
    for a kind whose candidates explain nothing). Each harmonic of a coupling counts as a kind (`family`)."""
    taken = {library[g].family for g in selected}
    best: dict[tuple[str, int], int] = {}
    for g, c in enumerate(library):
        if c.family not in taken and alone[g] > 0 and (c.family not in best or alone[g] > alone[best[c.family]]):
            best[c.family] = g
    return sorted(best.values(), key=lambda g: -alone[g])


def _best_of_kind(
    c: Candidate,
    d: int,
    names: list[str],
    alone: float,
    coef: list[float],
    inclusion: float,
    residual_rms: float,
    threshold: float,
    min_gain: float,
) -> Finding:
    """The finding of `c`, the best candidate of its kind on row `d` that the joint fit did not select: its
    coefficients fitted alone, never accepted by the screen; handed to the held-out judgement if it explains at
    least `min_gain` of the row alone (a delayed feedback only if no other kind passes there)."""
    if alone < min_gain:
        why = f"explains {alone:.1%} of the residual alone, below {min_gain:.0%}: not tested on held-out data"
    elif c.kind == "DelayedFeedback":
        why = "tested on held-out data if no other kind passes there"
    else:
        why = "tested on held-out data"
    return Finding(
        target=d,
        label=c.label(names, d),
        kind=c.kind,
        coef=coef,
        interval=[],
        gain=alone,
        explained_rms=residual_rms * math.sqrt(max(alone, 0.0)),
        alone=alone,
        inclusion=inclusion,
        threshold=threshold,
        accepted=False,
        reason=f"best of its kind on this row, not selected by the joint BIC fit (coefficients fitted alone): {why}",
        effect=c.effect_config(coef, d, names),
        selected=False,
    )


def _finding(
    c: Candidate,
    g: int,
    d: int,
    names: list[str],
    sel: Selection,
    alone: list[float],
    freq: dict[int, float],
    ci: list[tuple[float, float]],
    residual_rms: float,
    threshold: float,
    bars: _Bars,
) -> Finding:
    """The finding of candidate `c` (group `g` of the selection) on state row `d`, accepted if it clears `bars`."""
    excludes_zero = any(lo > 0 or hi < 0 for lo, hi in ci)
    part = residual_rms * math.sqrt(sel.gains[g])
    min_gain, null_factor = bars.min_gain, bars.null_factor
    checks = [
        (sel.gains[g] >= min_gain, f"explains {sel.gains[g]:.1%} of the residual, below {min_gain:.0%}"),
        (
            part >= threshold,
            f"accounts for an RMS of {part:.3g}, below {null_factor:g}× the null level "
            f"({threshold:.3g}): indistinguishable from noise and discretisation error",
        ),
        (freq[g] >= bars.min_inclusion, f"selected in only {freq[g]:.0%} of bootstrap resamples"),
        (excludes_zero, "its bootstrap interval includes zero"),
    ]
    failed = [why for ok, why in checks if not ok]
    return Finding(
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


def _refit_named(
    diag: Diagnosis,
    library: list[Candidate],
    res: Residual,
    keep: torch.Tensor,  # [B] finite trajectories
    base: torch.Tensor | None,  # [B, T-1, N, D, P] nuisance columns
    n_shared: int,
    model: Model,
    data: Trajectories,
    min_gain: float,
) -> None:
    """Refit the accepted findings together, then confirm them through the model's integration of a step, until
    no more is dropped (`mpsim.diagnose.refit`); updates `diag` in place."""
    while diag.accepted and not joint_refit(diag, library, res, keep, base, n_shared, model):
        pass  # an effect whose coefficient was not stable was dropped: refit the others
    while diag.accepted and not confirm_by_integration(diag, library, model, data, base, min_gain):
        while diag.accepted and not joint_refit(diag, library, res, keep, base, n_shared, model):
            pass


def _null_check(model, data, omegas, delays, kinds, represented, sigma, seed, phased=None, segment=None):
    """Run the pipeline on data simulated from the model itself, measured as the data were (their noise level,
    quantisation step, and unmeasured states estimated again: `mpsim.data.measurement.as_measured`).

    With `segment` shorter than the records (a chaotic system) the simulation restarts from the observed state
    every `segment` steps, so that it stays on the data's attractor (a whole-record simulation of a chaotic
    model leaves it, and its residual there says nothing about the data); the steps that end on a restart are a
    jump, not the model's step, and are left out of every fit.

    Returns:
        ([D] residual RMS on the null data (after the base fit), [D] the largest RMS any candidate explains there).
    """
    pred, jumps = _null_simulation(model, data, segment)
    gen = torch.Generator().manual_seed(seed + 1)
    null = Trajectories(
        t=data.t,
        x=as_measured(pred, data.t, data, torch.as_tensor(sigma, dtype=torch.float64).reshape(-1), gen),
        edge_index=data.edge_index,
        u=data.u,
        node_features=data.node_features,
        meta=data.meta,
    )
    res = one_step_residual(model, null)
    keep = torch.isfinite(res.r).flatten(1).all(dim=1)
    library = build_library(null, omegas, delays, kinds, phased)
    library += drift_candidates(model, null, kinds) + input_candidates(model, null, kinds)
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
        y, groups, base_d = target_rows(library, res, d, keep, base)
        y, groups = project(y, groups, base_d)
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
    pred, _ = rollout(model, data)
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
