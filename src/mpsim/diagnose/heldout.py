"""Acceptance by held-out prediction, and the three verdicts.

The one-step screen (`find_effects`) proposes candidates; here each one is *tested*: added to the model with
its coefficients fitted by multiple shooting on held-in data (the model's own white-box parameters refit
alongside), and named only if it lowers the held-out multi-step error by more than the same fit achieves on
null data (the model's own simulation plus the data's noise level) plus `margin` paired standard errors.
Without a candidate the model is refit the same way (its own parameters only), so an effect never gets the
credit for a plain refit.

Verdicts (each with its numbers; distinct exit codes):

| verdict | when | exit |
|---|---|---|
| effects named | named effects remove ≥ `min_explained` of the held-out error above the null level | 0 |
| nothing missing | the refit model's held-out error is at the null level (or below `tolerance`) | 10 |
| unexplained structured residual | above the null level and no candidate (set) explains it | 11 |
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field, replace
from typing import Any

import torch

from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.findings import Diagnosis, Finding
from mpsim.diagnose.levels import NOISE_DOMINATED, inflated_null, noise_dominated
from mpsim.diagnose.library import Candidate
from mpsim.diagnose.params import DiagnoseParams
from mpsim.diagnose.shooting import (
    PER_WINDOW_BELOW,
    heldout_errors,
    horizon_from_data,
    null_data,
    own_parameters,
    scored_window,
    shooting_fit,
)
from mpsim.diagnose.trial import FAILED, NOT_TESTED, Trial, TrialSetting, try_candidate
from mpsim.errors import ConfigError, did_you_mean
from mpsim.models.base import Model

EFFECTS_NAMED, NOTHING_MISSING, UNEXPLAINED = "effects named", "nothing missing", "unexplained structured residual"
EXIT_CODES = {EFFECTS_NAMED: 0, NOTHING_MISSING: 10, UNEXPLAINED: 11}
#: a simpler kind is preferred when its held-out error is within this factor of the best candidate's
SIMPLER_WITHIN = 1.25


def dynamic_rows(model: Model, data: Trajectories, targets: list[str] | None) -> list[int]:
    """State rows to search: `targets` if given, else every row except the kinematic ones (declared by the
    model — `model=equations` specs, white-box models whose equation for a state is another state — or by the
    data's metadata `kinematic: [...]`)."""
    names = list(data.state_names)
    if targets:
        for name in targets:
            if name not in names:
                raise ConfigError(
                    f"diagnose.targets names {name!r}, which is not a state.{did_you_mean(name, names)} "
                    f"States: {names}."
                )
        return [names.index(n) for n in targets]
    kinematic = set(getattr(model, "kinematic_states", None) or []) | set(data.meta.get("kinematic") or [])
    rows = [d for d, n in enumerate(names) if n not in kinematic and d < state_rows(model, data)]
    return rows or list(range(len(names)))


def state_rows(model: Model, data: Trajectories) -> int:
    """How many of the data's columns are the model's states (effects act on these; a spec's `outputs:` columns
    follow them and are what the sensors read, not states)."""
    spec = getattr(model, "spec", None)
    if getattr(model, "output_field", None) is not None and spec is not None:
        return int(spec.state_dim)
    return data.state_dim


@dataclass
class Judgement:
    """The held-out verdict and everything it rests on."""

    verdict: str
    horizon: int
    error_given: float  # held-out multi-step MSE of the model as given
    error_refit: float  # ... after refitting its own parameters by multiple shooting
    error_null: float  # ... of the refit model on null data (its own simulation plus the noise level)
    error_final: float  # ... with the named effects
    explained: float  # share of (refit − null) removed by the named effects
    trials: list[Trial] = field(default_factory=list)
    model: Model | None = None  # the refit model with the named effects (never worse on held-out data)
    notes: list[str] = field(default_factory=list)
    measured: dict[str, Any] = field(default_factory=dict)  # unmeasured states: which were measured, how estimated

    @property
    def exit_code(self) -> int:
        return EXIT_CODES[self.verdict]

    @property
    def named(self) -> list[Trial]:
        return [t for t in self.trials if t.accepted] if self.verdict == EFFECTS_NAMED else []

    def as_dict(self) -> dict[str, Any]:
        out = {k: v for k, v in self.__dict__.items() if k not in ("model", "trials")}
        out["trials"] = [t.as_dict() for t in self.trials]
        out["named"] = [t.label for t in self.named]
        return out


def judge(
    model: Model,
    diag: Diagnosis,
    library: list[Candidate],
    train: Trajectories,
    test: Trajectories,
    params: DiagnoseParams,
    seed: int = 0,
    test_candidates: bool = True,
) -> Judgement:
    """Test the screen's candidates (the best of each kind on each row: `_ranked`) on held-out prediction; name the
    ones that pass, greedily, and return the verdict with the model that carries them. With
    `test_candidates=False` only the levels are measured (given, refit, null) and the verdict is *nothing
    missing* or *unexplained*: the caller tests the candidates another way (by finetuning a network). With
    unmeasured states the judgement says which states were measured and how the others were handled."""
    out = _judge(model, diag, library, train, test, params, seed, test_candidates)
    window = scored_window(len(test), test.n_times, out.horizon)
    if window < out.horizon:
        out.notes.append(
            f"{len(test)} held-out records (fewer than {PER_WINDOW_BELOW}): held-out errors are scored over windows of "
            f"{window} steps, each window a unit of the test with its dependence on its neighbours estimated "
            "(the fits use windows of the horizon)"
        )
    out.measured = test.measured_states()
    if out.measured:
        out.notes.append(latent_note(out.measured))
    return out


def latent_note(measured: dict[str, Any]) -> str:
    """How unmeasured states enter the judgement (`measured`: `Trajectories.measured_states`)."""
    how = "; ".join(f"{s}: {text}" for s, text in measured["estimated"].items())
    return (
        f"measured states {measured['observed']}: errors are on these only. Not measured — {how}. Each window's "
        "unmeasured start is fitted to the window's measured samples: jointly with the parameters in every "
        "multiple-shooting fit (variable projection), with the model fixed on held-out windows (state estimation)"
    )


def _judge(
    model: Model,
    diag: Diagnosis,
    library: list[Candidate],
    train: Trajectories,
    test: Trajectories,
    params: DiagnoseParams,
    seed: int,
    test_candidates: bool,
) -> Judgement:
    train = train.subset(slice(0, params.fit_trajectories))  # a handful of parameters: a few records suffice
    horizon = params.horizon or diag.horizon or horizon_from_data(model, train, params.vpt_threshold)
    s, given = _levels(model, diag, train, test, horizon, params, seed)
    horizon = s.horizon  # no longer than the refit model tracks its own noisy data (`_null_twin`)
    e_base, e_null = float(s.e_base.mean()), float(s.e_null.mean())
    floor = null_floor(s)
    inflated = inflated_null(s, diag.noise_std)
    if e_base <= floor and not inflated:  # at the null level: nothing to test
        return Judgement(NOTHING_MISSING, horizon, given, e_base, e_null, e_base, 0.0, [], s.base, [])
    if not test_candidates:
        note = "candidates are tested by finetuning the model with each one against the same finetune without it"
        return Judgement(UNEXPLAINED, horizon, given, e_base, e_null, e_base, 0.0, [], s.base, [note])
    current, e_current, trials = _add_greedily(s, _ranked(diag, library, params))
    out = _verdict(s, given, floor, current, e_current, trials)
    if out.verdict == NOTHING_MISSING and inflated:  # complete only where the sensor's noise would allow it
        out = replace(out, verdict=UNEXPLAINED, notes=[*out.notes, inflated])
    return replace(out, notes=out.notes + failed_note(trials))


def failed_note(trials: list[Trial]) -> list[str]:
    """A note naming the candidates whose trial failed numerically (none: no note)."""
    failed = [t for t in trials if t.failure]
    if not failed:
        return []
    return [
        f"{len(failed)} candidate{'s' if len(failed) > 1 else ''} failed and {'were' if len(failed) > 1 else 'was'} "
        "rejected (a fit that diverges or a rollout the solver gives up on is the candidate's failure; the others "
        "were judged without it): " + "; ".join(f"{t.label} — {t.failure.removeprefix(FAILED + ': ')}" for t in failed)
    ]


def _levels(
    model: Model,
    diag: Diagnosis,
    train: Trajectories,
    test: Trajectories,
    horizon: int,
    params: DiagnoseParams,
    seed: int,
) -> tuple[TrialSetting, float]:
    """The model with its own parameters refit by multiple shooting (never worse than the model as given on
    held-out data), its held-out errors, and null records simulated by it with the data's noise level; with the
    held-out MSE of the model as given. The held-out windows are at most `horizon` steps, and no longer than
    the refit model tracks its own noisy null records (`_null_twin`)."""
    noise = torch.tensor(diag.noise_std, dtype=torch.float64)
    base = copy.deepcopy(model)
    shooting_fit(base, train, min(horizon, params.fit_window), own_parameters(base), params.shooting_iters, False)
    horizon, null_train = _null_twin(base, train, noise, horizon, params, seed + 11)
    window = scored_window(len(test), test.n_times, horizon)  # few held-out records: shorter windows, more of them
    given = float(heldout_errors(model, test, horizon, window).mean())
    e_base = heldout_errors(base, test, horizon, window)
    if not float(e_base.mean()) <= given:  # the refit never makes the starting point worse
        base, e_base = copy.deepcopy(model), heldout_errors(model, test, horizon, window)
        null_train = null_data(base, train, noise, seed + 11, segment=horizon)
    null_test = null_data(base, test, noise, seed + 12, segment=horizon)
    e_null = heldout_errors(base, null_test, horizon, window)
    setting = TrialSetting(
        base, e_base, e_null, train, test, null_train, null_test, horizon, params, diag.state_names, window
    )
    return setting, given


#: the held-out horizon ends where the null twin's error passes this share of `vpt_threshold` (`_null_twin`)
NULL_TRACKING = 1 / 3


def _null_twin(
    base: Model, train: Trajectories, noise: torch.Tensor, horizon: int, params: DiagnoseParams, seed: int
) -> tuple[int, Trajectories]:
    """(the held-out horizon, null records of the held-in data cut to it). On a chaotic system even the exact
    model loses its own noisy data after a while: held-out windows longer than that saturate for every model,
    the right one included, and the share of the error it removes means nothing. So the horizon is at most the
    time the refit model tracks its own null data (`noise`: [D] the data's noise level): the step where the null
    windows' normalised RMS error first passes `NULL_TRACKING` × `vpt_threshold`, or twice its first step's
    (the noise level) if that is larger. Well inside the valid prediction time, where an error still grows in
    proportion to its cause: there a near-right model's error is near the null level, which the share explained
    measures. A horizon set by hand (`diagnose.horizon`) is kept; where the model never loses its own data (not
    chaotic) nothing changes."""
    null_train = null_data(base, train, noise, seed, segment=horizon)
    if params.horizon is not None:
        return horizon, null_train
    tracked = horizon_from_data(base, null_train, NULL_TRACKING * params.vpt_threshold, above_first=2.0)
    if tracked >= horizon:
        return horizon, null_train
    return tracked, null_data(base, train, noise, seed, segment=tracked)


#: candidates to try, each with its candidate column group: (the ones tried first, the ones tried if none passes)
Ranked = tuple[list[tuple[Finding, Candidate]], list[tuple[Finding, Candidate]]]


#: kinds whose best candidate is tried on held-out data whatever share of the one-step residual it explains, and why
ALWAYS_TRIED = {
    "InputGain": (
        ": tested on held-out data all the same: a gain per recording shows in the one-step residual only where the "
        "input is large, and the part all recordings share is the model's own input coefficient (projected out)"
    ),
}


def _ranked(diag: Diagnosis, library: list[Candidate], params: DiagnoseParams) -> Ranked:
    """The best candidate of each effect kind on each searched row; held-out data decide between them.

    The one-step screen picks which term of a kind stands for it (its BIC-selected one, screened ones first;
    for a kind the joint fit did not select, the one that explains most of the row alone, if that is at least
    `min_gain`), not which kind: on data stepped by another integrator a delayed copy of the velocity can
    explain more of the one-step residual than the damping it imitates, and only the held-out trial tells them
    apart. So every kind gets a trial, at most one per (kind, row) — the number of trials is bounded by kinds
    × searched rows. Each harmonic k of a phase coupling counts as a kind of its own (`Candidate.family`): the
    second harmonic of a sin coupling gets its trial even where the first explains more of the one-step
    residual. A delayed copy of a state imitates many terms within a step and needs the slow delay
    integrator: delayed candidates are tried only when none of the others passes. On a row whose one-step residual
    is noise-dominated (`noise_dominated`: a differentiated residual of sparse or noisy samples, where a missing
    term explains a few percent) every kind's best candidate is tried, whatever share it explains: multiple
    shooting on held-in windows and the held-out error see what the differentiated residual hides."""
    labels = {c.label(diag.state_names): c for c in library}
    best: dict[tuple[tuple[str, int], int], Finding] = {}  # one per (kind and harmonic, row)
    noisy = noise_dominated(diag)
    for f in sorted(diag.findings, key=lambda f: (not f.accepted, not f.selected, -f.gain)):
        cand = labels.get(f.label.split(": ", 1)[1])
        always = cand is not None and cand.kind in ALWAYS_TRIED and f.alone > 0
        if cand is not None and (
            f.selected or f.alone >= params.min_gain or (f.target in noisy and f.alone > 0) or always
        ):
            if (cand.family, f.target) not in best and not f.selected and f.alone < params.min_gain:
                f.reason = f.reason.replace(
                    ": not tested on held-out data",
                    ALWAYS_TRIED[cand.kind]
                    if always
                    else ": tested on held-out data all the same, as its row's one-step residual is noise-dominated "
                    f"(RMS within {NOISE_DOMINATED:g}× the null data's)",
                )
            best.setdefault((cand.family, f.target), f)
    plain = [f for f in best.values() if f.kind != "DelayedFeedback"]
    delayed = [f for f in best.values() if f.kind == "DelayedFeedback"]
    pending = [(f, labels[f.label.split(": ", 1)[1]]) for f in plain]
    later = [(f, labels[f.label.split(": ", 1)[1]]) for f in delayed]
    return (later, []) if not pending else (pending, later)


def _add_greedily(s: TrialSetting, ranked: Ranked) -> tuple[Model, torch.Tensor, list[Trial]]:
    """The plain kinds added greedily (`_greedy`; the delayed ones only if none of them passes). A delayed copy
    of a state is imitated in part by plain kinds (a damping and a stiffness at one frequency): where plain kinds
    pass but leave the held-out error above the null level, the delayed candidates are tried too, from the refit
    model, and they replace the plain ones only if they predict held-out data better by more than
    `SIMPLER_WITHIN` and come within `DELAY_NEAR_NULL` × the null floor (the only way a delay can be named)."""
    pending, later = ranked
    current, e_current, trials = _greedy(s, pending, later)
    floor = null_floor(s)
    tried = any(t.kind == "DelayedFeedback" for t in trials)  # none of the plain kinds passed: tried already
    if tried or not later or not any(t.accepted for t in trials) or float(e_current.mean()) <= floor:
        return current, e_current, trials
    d_current, d_e, d_trials = _greedy(s, later, [])
    plain, delayed = float(e_current.mean()), float(d_e.mean())
    named = [t for t in d_trials if t.accepted]
    if named and delayed <= DELAY_NEAR_NULL * floor and SIMPLER_WITHIN * delayed < plain:
        for t in trials:
            if t.accepted:
                t.accepted = False
                t.reason = (
                    f"passes, but leaves the held-out MSE at {plain:.3g}, above the null level, where "
                    f"{named[0].label} brings it to {delayed:.3g}: the plain kinds imitated the delay in part; "
                    + t.reason
                )
        return d_current, d_e, trials + d_trials
    for t in named:
        t.accepted = False
        t.reason = (
            f"tried because the plain kinds left the held-out MSE at {plain:.3g} (above the null level), but "
            f"with it {delayed:.3g}: not better by {SIMPLER_WITHIN:g}× and within {DELAY_NEAR_NULL:g}× of the null "
            f"floor {floor:.3g}; " + t.reason
        )
    return current, e_current, trials + d_trials


def _greedy(
    s: TrialSetting, pending: list[tuple[Finding, Candidate]], later: list[tuple[Finding, Candidate]]
) -> tuple[Model, torch.Tensor, list[Trial]]:
    """Forward selection on held-out data: each candidate is first tried alone on the refit model; the best passing
    one is added — the simplest kind among those within `SIMPLER_WITHIN` of the best held-out error or at the null
    level (`null_floor`: below it the difference between them is noise) — and every other candidate that was
    tested (passing or not: a second effect can be invisible until the first is in, an output offset under a
    cubic stiffness) is tried again on top of it, until none passes or the error is at the null level: (the model
    with the added candidates, its held-out errors, every candidate's last trial, the added ones in the order
    they were added). A candidate whose trial failed numerically, or that could not be tested, is not tried
    again. A more complex kind set aside for an equivalent simpler one is reported as indistinguishable from it
    on these data."""
    current, e_current = s.base, s.e_base
    floor = null_floor(s)
    aside: dict[int, str] = {}  # id of a finding -> why its kind was set aside for a simpler, equivalent one
    last: dict[int, Trial] = {}  # id of a finding -> its latest trial (not added)
    added: list[Trial] = []
    while pending:
        tried = [(f, c, *try_candidate(s, current, e_current, c, f)) for f, c in pending]
        passing = [t for t in tried if t[2].accepted]
        for t in tried:
            if not t[2].accepted and id(t[0]) in aside:  # tried again on top of its simpler equivalent, and failed
                t[2].reason = aside[id(t[0])] + "; on top of it: " + t[2].reason
            elif not t[2].accepted and added and id(t[0]) in last:
                t[2].reason = f"tried again on top of {', '.join(a.label for a in added)}: " + t[2].reason
            last[id(t[0])] = t[2]
        if not passing and later and current is s.base:
            pending, later = later, []
            continue
        if not passing:
            break
        best_err = min(t[2].error_after for t in passing)
        close = [t for t in passing if t[2].error_after <= max(SIMPLER_WITHIN * best_err, floor)]
        chosen = min(close, key=lambda t: (t[1].complexity, t[2].error_after))  # k = 1 before higher harmonics
        added.append(chosen[2])
        last.pop(id(chosen[0]))
        for t in close:  # a more complex kind that predicts as well: the two are indistinguishable on these data
            if t[1].complexity > chosen[1].complexity:
                aside[id(t[0])] = _indistinguishable_text(t[2], chosen[2], best_err, floor)
        current, e_current = chosen[3], chosen[4]
        chosen[2].reason += f" (added {len(added)}{'st' if len(added) == 1 else 'nd' if len(added) == 2 else 'th'})"
        if (chosen[2].kind == "PeriodicForcing" and "phases" in chosen[2].effect) or chosen[2].kind == "InputGain":
            e_current = torch.full_like(s.e_base, chosen[2].error_after)  # measured after the warm-up window
            break  # its phases (gains) belong to the held-in recordings: nothing more is added on top of it
        if float(e_current.mean()) <= floor:  # at the null level: nothing is left for another effect to explain
            for t in passing:
                if t is not chosen:
                    t[2].accepted = False
                    t[2].reason = (
                        aside[id(t[0])]
                        if id(t[0]) in aside
                        else (
                            f"passes, but {chosen[2].label} (the simplest kind at the null level or the best) "
                            f"already brings the held-out MSE to {float(e_current.mean()):.3g}, at the null level "
                            f"(≤ {floor:.3g}): " + t[2].reason
                        )
                    )
            break
        # every other tested candidate is tried again on top of the chosen one
        pending = [(t[0], t[1]) for t in tried if t is not chosen and _retry(t[2])]
    for rest in last.values():  # whatever was not added is not named, however its last trial scored
        if rest.accepted:
            rest.accepted = False
            rest.reason = f"passes, but the selection stopped at {added[-1].label}: " + rest.reason
    return current, e_current, added + list(last.values())


def _retry(t: Trial) -> bool:
    """Whether a candidate that was not added is tried again on top of the one that was: not when its trial failed
    numerically or could not be run on these records."""
    return not t.failure and not t.reason.startswith(NOT_TESTED) and not math.isnan(t.error_after)


def _indistinguishable_text(other: Trial, chosen: Trial, best: float, floor: float) -> str:
    """Why `other`, a more complex kind that passed alone, was set aside for the simpler `chosen` one."""
    within = (
        f"both at the null level (≤ {floor:.3g})"
        if max(other.error_after, chosen.error_after) <= floor
        else f"within {SIMPLER_WITHIN:g}× of the best, {best:.3g}"
    )
    return (
        f"passes alone, but predicts held-out data as well as the simpler {chosen.label} (held-out MSE "
        f"{other.error_after:.3g} against {chosen.error_after:.3g}, {within}): the two kinds are indistinguishable "
        f"on these data, and the simpler one ({chosen.kind}) is named"
    )


def null_floor(s: TrialSetting) -> float:
    """The held-out MSE at or below which a model is at the null level: `structured_factor` × the refit model's
    error on null data, or `tolerance` RMSE."""
    return max(s.params.structured_factor * float(s.e_null.mean()), s.params.tolerance**2)


#: a named delayed feedback must bring the held-out MSE within this factor of the null floor (issue 61: a delay at
#: half its value, and an input gain imitated by a delay, each removed most of the excess but stayed 2000× above it)
DELAY_NEAR_NULL = 10.0


def _verdict(
    s: TrialSetting, given: float, floor: float, current: Model, e_current: torch.Tensor, trials: list[Trial]
) -> Judgement:
    """The verdict on the trials: the named effects must remove `min_explained` of the error above the null
    level (or bring it to the floor), and a named delayed feedback must bring it within `DELAY_NEAR_NULL` × the
    floor; otherwise nothing is named and the refit model is kept."""
    params = s.params
    refit, final, null = float(s.e_base.mean()), float(e_current.mean()), float(s.e_null.mean())
    excess = max(refit - null, 1e-300)
    explained = (refit - final) / excess if any(t.accepted for t in trials) else 0.0
    notes = []
    # a delayed copy of a state imitates other terms in part (damping within a step, a gain, a lag): it is named only
    # if it brings the held-out error near the null level, not for removing most of the excess
    delay_far = final > DELAY_NEAR_NULL * floor and any(t.accepted and t.kind == "DelayedFeedback" for t in trials)
    if any(t.accepted for t in trials) and (final <= floor or explained >= params.min_explained) and not delay_far:
        verdict = EFFECTS_NAMED
    elif refit <= floor:
        verdict = NOTHING_MISSING
        for t in trials:
            if t.accepted:  # below the null level nothing is named, however it scored
                t.accepted, t.reason = False, "the model is already at the null level: " + t.reason
        current = s.base
    else:
        verdict = UNEXPLAINED
        for t in trials:
            if t.accepted:
                t.accepted = False
                t.reason = (
                    f"helps on held-out data but leaves the held-out MSE at {final:.3g}, {final / floor:.3g}× the "
                    f"null floor {floor:.3g}: a delayed feedback is named only within {DELAY_NEAR_NULL:g}× of it (a "
                    "delayed copy of a state imitates other terms in part), so this is a partial fit, not a finding"
                    if delay_far
                    else f"helps on held-out data but leaves {1 - explained:.0%} of the error above the null level "
                    f"unexplained (needs ≥ {params.min_explained:.0%}): a partial fit, not a finding"
                )
        notes.append(_best_text(trials, refit, null))
        current = s.base
    return Judgement(
        verdict, s.horizon, given, refit, null, final if verdict == EFFECTS_NAMED else refit, explained, trials,
        current, notes,
    )  # fmt: skip


def _best_text(trials: list[Trial], refit: float, null: float) -> str:
    untested = [t for t in trials if t.reason.startswith(NOT_TESTED)]
    tested = [t for t in trials if not t.reason.startswith(NOT_TESTED) and not t.failure]
    skipped = f"{', '.join(t.label for t in untested)} {untested[0].reason}" if untested else ""
    if not tested:
        return skipped or "no candidate was left to test"
    best = min(tested, key=lambda t: t.error_after)
    left = (best.error_after - null) / max(refit - null, 1e-300)
    return (
        f"best candidate {best.label}: held-out MSE {refit:.3g} → {best.error_after:.3g} (null level {null:.3g}); "
        f"it would leave {max(left, 0):.0%} of the excess" + (f"; {skipped}" if skipped else "")
    )
