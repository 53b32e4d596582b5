"""Acceptance for black-box models: candidate plus finetune against the same finetune without it.

A network with no input for an effect (a drive, to a network without a clock) learns part of it as a function of
the state. Fitted with the network frozen (the held-out judgement of `heldout.judge`), the effect then double-counts
what the network already does, and even the true effect can make held-out prediction worse. So with `fix=true`, a
model with trainable parameters beyond its named physical ones is also judged this way:

- the *control*: the model finetuned without any candidate (same epochs, learning rate and seed as every
  candidate's finetune), so that an effect never gets the credit for more training;
- each screened candidate (at most `max_candidates`, strongest share of its row first) added to the model with its
  screen coefficients and finetuned; a drive with a phase per recording is tried with one shared phase when the
  recordings' phases agree (mean resultant length ≥ `PHASES_AGREE`), since per-recording phases cannot be carried
  to new data nor finetuned in shuffled batches; otherwise it is not finetuned, and the report says so;
- a candidate is named only if, on held-out recordings, its log error ratio against the control exceeds `margin`
  paired standard errors and it removes at least `min_explained` of the control's error above the null level.

The reported coefficients are those of the finetuned model, with 95 % intervals from the Gauss–Newton sandwich of
the multiple-shooting residuals at those values (the network held fixed).
"""

from __future__ import annotations

import copy
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.findings import Diagnosis, Finding
from mpsim.diagnose.heldout import EFFECTS_NAMED, UNEXPLAINED, failed_note
from mpsim.diagnose.library import Candidate
from mpsim.diagnose.params import DiagnoseParams
from mpsim.diagnose.shooting import NUMERICAL_FAILURES, failure_text, sandwich_stderr, window_error, with_effect
from mpsim.diagnose.stats import level_text, paired
from mpsim.diagnose.trial import FAILED, Trial, diverged_heldout, ran_off, reported
from mpsim.errors import DivergenceError
from mpsim.models.base import Model

#: a phased drive is tried with one shared phase when the mean resultant length of its per-recording phases
#: (amplitude-weighted) is at least this: the recordings share a clock
PHASES_AGREE = 0.9

#: finetune(model, tag) -> (finetuned model, its checkpoint path); `tag` names the run ("round1/control", ...)
TaggedFinetune = Callable[[Model, str], tuple[Model, str]]
#: finetune_all([(model, tag), ...]) -> for each, (finetuned model, checkpoint path) or the DivergenceError of its
#: run, in order; the runs are independent (same epochs, learning rate and seed), so they may run at once
FinetuneAll = Callable[[list[tuple[Model, str]]], list[tuple[Model, str] | DivergenceError]]
#: the one-step screen of a model on held-in data: (diagnosis, candidate library)
Screened = tuple[Diagnosis, list[Candidate]]


@dataclass
class FinetuneJudgement:
    """The finetune comparison and everything it rests on (held-out multi-step MSE, normalised units)."""

    verdict: str
    horizon: int
    error_given: float  # the model as given
    error_control: float  # finetuned without a candidate
    error_null: float  # null level (the frozen judgement's)
    error_final: float  # the named candidate's finetuned model (the control's error when nothing is named)
    explained: float  # share of (control − null) removed by the named candidate
    trials: list[Trial] = field(default_factory=list)
    model: Model | None = None  # the finetuned model with the named effect
    checkpoint: str | None = None
    control_checkpoint: str | None = None
    notes: list[str] = field(default_factory=list)
    rest: Screened | None = None  # the screen of the named candidate's finetuned model, when it was run

    @property
    def named(self) -> list[Trial]:
        return [t for t in self.trials if t.accepted] if self.verdict == EFFECTS_NAMED else []

    def as_dict(self) -> dict[str, Any]:
        out = {k: v for k, v in self.__dict__.items() if k not in ("model", "trials", "rest")}
        out["trials"] = [t.as_dict() for t in self.trials]
        out["named"] = [t.label for t in self.named]
        return out


def shared_phase(finding: Finding) -> tuple[list[float], float]:
    """([a, b] of one shared-phase drive, mean resultant length) from a phased drive's per-recording (a, b) pairs."""
    pairs = torch.tensor(finding.coef, dtype=torch.float64).reshape(-1, 2)  # [B, 2]
    mean = pairs.mean(dim=0)
    agree = float(mean.norm() / pairs.norm(dim=1).mean().clamp(min=1e-300))
    return mean.tolist(), agree


def finetune_candidates(
    diag: Diagnosis, library: list[Candidate], params: DiagnoseParams
) -> tuple[list[tuple[Finding, Candidate, list[float], str]], list[str]]:
    """The screened candidates a finetune can carry, strongest share of their row first: (finding, candidate,
    starting coefficients, label); and notes on the ones left out."""
    labels = {c.label(diag.state_names): c for c in library}
    out: list[tuple[Finding, Candidate, list[float], str]] = []
    notes: list[str] = []
    seen: set[str] = set()
    for f in sorted(diag.findings, key=lambda f: -f.gain):
        cand = labels.get(f.label.split(": ", 1)[1])
        if not f.accepted or cand is None or f.kind == "DelayedFeedback":
            continue
        coef, label = list(f.coef), f.label
        if cand.params.get("phased"):
            coef, agree = shared_phase(f)
            if agree < PHASES_AGREE:
                notes.append(
                    f"{f.label}: the recordings' phases disagree (mean resultant length {agree:.2f} < {PHASES_AGREE}), "
                    "so the drive cannot be carried by one model and is not finetuned"
                )
                continue
            cand = Candidate("PeriodicForcing", None, {"omega": cand.params["omega"]})
            label = cand.label(diag.state_names, f.target)
            notes.append(f"{f.label}: the recordings' phases agree ({agree:.2f}); tried with one shared phase")
        if label in seen:
            continue
        seen.add(label)
        out.append((f, cand, coef, label))
        if len(out) >= params.max_candidates:
            break
    return out, notes


def serial(finetune: TaggedFinetune) -> FinetuneAll:
    """`finetune_all` that runs one finetune after another in this process."""

    def run(jobs: list[tuple[Model, str]]) -> list[tuple[Model, str] | DivergenceError]:
        out: list[tuple[Model, str] | DivergenceError] = []
        for model, tag in jobs:
            try:
                out.append(finetune(model, tag))
            except DivergenceError as exc:
                out.append(exc)
        return out

    return run


def _slug(label: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "_", label).strip("_")[:60]


def judge_by_finetune(
    model: Model,
    diag: Diagnosis,
    library: list[Candidate],
    train: Trajectories,
    test: Trajectories,
    horizon: int,
    error_null: float,
    params: DiagnoseParams,
    finetune: FinetuneAll,
    tag: str,
    log: Callable[[str], None] = lambda _: None,
    rescreen: Callable[[Model], Screened] | None = None,
) -> FinetuneJudgement:
    """Finetune `model` without a candidate (the control) and with each screened candidate; name the best one if
    it beats the control on held-out recordings (see the module docstring)."""
    candidates, notes = finetune_candidates(diag, library, params)
    given = float(window_error(model, test, horizon).mean())
    if not candidates:  # nothing to compare: no control is trained
        notes.append(
            "no screened candidate to finetune (no control was trained): the error above the null level (the "
            "model's own simulation, which cannot show a network's approximation error) has no structure the "
            "screen recognises — the network's own error or an effect outside the library; nothing is claimed"
        )
        return FinetuneJudgement(UNEXPLAINED, horizon, given, given, error_null, given, 0.0, [], notes=notes)
    jobs = [(copy.deepcopy(model), f"{tag}/control")]
    effects = [cand.make_effect(coef, f.target, diag.state_names) for f, cand, coef, _ in candidates]
    jobs += [(with_effect(model, e), f"{tag}/{_slug(c[3])}") for c, e in zip(candidates, effects, strict=True)]
    log(f"{tag}: finetuning the control (no candidate) and with {'; '.join(c[3] for c in candidates)}")
    outcomes = finetune(jobs)
    if isinstance(outcomes[0], DivergenceError):
        raise DivergenceError(f"the finetune of the control diverged: {outcomes[0]}")
    control, control_path = outcomes[0]
    e_control = window_error(control, test, horizon)
    err_control = float(e_control.mean())
    excess = max(err_control - error_null, 1e-300)
    trials: list[Trial] = []
    models: dict[int, tuple[Model, str]] = {}
    for (_, cand, _, label), effect, outcome in zip(candidates, effects, outcomes[1:], strict=True):
        if isinstance(outcome, DivergenceError):  # a wrong candidate can derail training: rejected, not an error
            trials.append(
                _diverged(label, cand.kind, effect, err_control, f"the finetune with it diverged ({outcome})")
            )
            continue
        try:
            trial = _finetuned_trial(
                label, cand.kind, outcome[0], e_control, train, test, horizon, error_null, excess, params
            )
        except NUMERICAL_FAILURES as exc:  # its failure is its own: the other candidates are judged
            why = f"{FAILED} while judging the model finetuned with it: {failure_text(exc)}"
            trials.append(_diverged(label, cand.kind, effect, err_control, why))
            continue
        trials.append(trial)
        models[len(trials) - 1] = outcome
    notes += failed_note(trials)
    best = _best_of_round(trials)
    levels = (horizon, given, err_control, error_null)
    if best is None:
        return FinetuneJudgement(UNEXPLAINED, *levels, err_control, 0.0, trials, None, None, control_path, notes)
    chosen = trials[best]
    tuned, path = models[best]
    explained, rest = _check_named(chosen, tuned, err_control, excess, given, params, rescreen)
    if not chosen.accepted:
        return FinetuneJudgement(UNEXPLAINED, *levels, err_control, explained, trials, None, None, control_path, notes)
    return FinetuneJudgement(
        EFFECTS_NAMED, *levels, chosen.error_after, explained, trials, tuned, path, control_path, notes, rest
    )


def _finetuned_trial(
    label: str,
    kind: str,
    tuned: Model,
    e_control: torch.Tensor,  # [B] held-out MSE of the control
    train: Trajectories,
    test: Trajectories,
    horizon: int,
    error_null: float,
    excess: float,
    params: DiagnoseParams,
) -> Trial:
    """The trial of a candidate finetuned with the network (`tuned`, its last effect) against the control."""
    err_control = float(e_control.mean())
    floor = max(error_null, 1e-14)
    e_after = window_error(tuned, test, horizon)
    p = paired(e_control, e_after, floor, params.margin)
    share = p.gain / excess
    fitted = tuned.effects[-1]
    free = [q for q in fitted.parameters() if q.requires_grad]
    values_now = torch.cat([q.detach().reshape(-1).double().cpu() for q in free]).tolist()
    stderr = sandwich_stderr(tuned, train.subset(slice(0, params.fit_trajectories)), params.fit_window, free)
    values, interval = reported(fitted, values_now, stderr)
    checks = [
        (math.isfinite(p.gain), "the finetuned model's held-out rollouts diverged"),
        (
            p.log_ratio > p.bar * p.log_ratio_se,
            f"held-out error ratio against the control e^{p.log_ratio:.3g} (± {p.log_ratio_se:.2g} in log) is not "
            f"above {p.bar:.3g} standard errors ({level_text(params.margin, p.n)})",
        ),
        (
            share >= params.min_gain,
            f"removes {share:.1%} of the control's held-out error above the null level, below {params.min_gain:.0%}",
        ),
    ]
    # rollouts that diverge with it (not in the control's) or values that ran off: the candidate's failure
    failure = diverged_heldout(e_control, e_after) or ran_off(values)
    failed = failure or [why for ok, why in checks if not ok]
    reason = "; ".join(failed) or (
        f"finetuned with it, held-out MSE {err_control:.3g} (control, finetuned without it) → "
        f"{float(e_after.mean()):.3g}"
    )
    return Trial(
        label=label,
        kind=kind,
        screened=True,
        effect=fitted.config(),
        values=values,
        interval=interval,
        error_before=err_control,
        error_after=float(e_after.mean()),
        gain=p.gain,
        gain_se=p.gain_se,
        null_gain=0.0,
        accepted=not failed,
        reason=reason,
        derived="finetuned with the network; compared with the same finetune without it (the control)",
        log_ratio=p.log_ratio,
        log_ratio_se=p.log_ratio_se,
        null_log_ratio=0.0,
        n_heldout=p.n,
        bar_se=p.bar,
        failure="; ".join(failure),
    )


def _best_of_round(trials: list[Trial]) -> int | None:
    """The index of the passing trial with the lowest held-out error (None if none passes); one effect per round:
    the other passing ones are reported, not named."""
    passing = [i for i, t in enumerate(trials) if t.accepted]
    best = min(passing, key=lambda i: trials[i].error_after) if passing else None
    for i in passing:
        if i != best:
            trials[i].accepted = False
            trials[i].reason = f"helps, but less than {trials[best].label} (named this round)"  # type: ignore[index]
    return best


def _check_named(
    chosen: Trial,
    tuned: Model,
    err_control: float,
    excess: float,
    given: float,
    params: DiagnoseParams,
    rescreen: Callable[[Model], Screened] | None,
) -> tuple[float, Screened | None]:
    """Whether the round's best candidate (finetuned model `tuned`) is named: it must beat the model as given
    and remove `min_explained` of the control's error above the null level, or leave nothing the screen of the
    finetuned model recognises. Rejects `chosen` in place if not; returns (its share explained, that screen)."""
    explained = (err_control - chosen.error_after) / excess
    rest: Screened | None = None
    left: list[str] = []
    if explained < params.min_explained and rescreen is not None and chosen.error_after < given:
        # null data of a network are its own simulation: they cannot show its approximation error, which a
        # finetune with the true effect still leaves. What is left counts as that error only if the screen of
        # the finetuned model finds no structure in it.
        rest = rescreen(tuned)
        left = [f.label for f in rest[0].findings if f.accepted]
        if not left:
            chosen.reason += (
                f"; it leaves {1 - explained:.0%} of the control's error above the null level, in which the screen "
                "of the finetuned model finds no structure (the network's own approximation error, which null data "
                "simulated by the model cannot show)"
            )
    if not chosen.error_after < given or (explained < params.min_explained and (rest is None or left)):
        chosen.accepted = False
        if not chosen.error_after < given:
            chosen.reason = f"beats the control but not the model as given ({given:.3g} → {chosen.error_after:.3g})"
        else:
            chosen.reason = (
                f"helps against the control but leaves {1 - explained:.0%} of its error above the null level "
                f"unexplained (needs ≥ {params.min_explained:.0%}): a partial fit, not a finding"
            ) + (f"; the screen of the finetuned model still finds {'; '.join(left)}" if left else "")
    return explained, rest


def _diverged(label: str, kind: str, effect: Any, before: float, why: str) -> Trial:
    """The trial of a candidate whose finetune diverged or whose judgement failed numerically (`why`)."""
    return Trial(
        label=label,
        kind=kind,
        screened=True,
        effect=effect.config(),
        values={},
        interval={},
        error_before=before,
        error_after=math.inf,
        gain=-math.inf,
        gain_se=math.inf,
        null_gain=0.0,
        accepted=False,
        reason=why,
        failure=why,
    )
