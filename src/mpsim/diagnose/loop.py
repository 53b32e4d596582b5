"""The residual loop as a library: screen → held-out judgement → (fix) add, finetune, diagnose again.

`run_loop` is what `mpsim diagnose` calls; the command layer only reads the config, supplies the finetune
(a trainer run that writes checkpoints) and writes the reports. The loop never hands back a model that is
worse on held-out data than the one it was given: a fix that does not help is reported as rejected, with its
numbers.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import torch

from mpsim.data.dataset import Splits
from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.findings import Diagnosis
from mpsim.diagnose.finetuned import FinetuneAll, FinetuneJudgement, judge_by_finetune, serial
from mpsim.diagnose.heldout import (
    EFFECTS_NAMED,
    EXIT_CODES,
    NOTHING_MISSING,
    Judgement,
    dynamic_rows,
    judge,
    state_rows,
)
from mpsim.diagnose.latent import fitted_latent
from mpsim.diagnose.library import Candidate, build_library
from mpsim.diagnose.nuisance import drift_candidates, input_candidates
from mpsim.diagnose.params import DiagnoseParams
from mpsim.diagnose.pernode import with_per_node
from mpsim.diagnose.residual import one_step_residual
from mpsim.diagnose.search import find_effects
from mpsim.diagnose.shooting import horizon_from_data, own_parameters, window_error
from mpsim.diagnose.trial import Trial
from mpsim.errors import DivergenceError
from mpsim.metrics import rollout_metrics, select_features, valid_prediction_time
from mpsim.models.base import Model
from mpsim.models.rollout import rollout

#: finetune(model with the named effects, tag) -> (finetuned model, its checkpoint path); the tag names the run
#: ("round1", "round1/control", "round1/<candidate>")
Finetune = Callable[[Model, str], tuple[Model, str]]
#: save(model, round number) -> checkpoint path of a model kept without finetuning
Save = Callable[[Model, int], str]


def holdout_metrics(model: Model, test: Trajectories, horizons: list[int], vpt_threshold: float) -> dict[str, Any]:
    """Held-out one-step error, rollout RMSE at fixed horizons and valid prediction time (normalised units), on
    the measured states. With unmeasured states each record's rollout starts from the latent state that fits its
    measured samples best, the model fixed (`diagnose.latent`); the one-step error steps from the data's estimate."""
    std = model.state_std.detach().cpu().double()
    observed = test.observed_index
    step = one_step_residual(model, test)
    one_step = select_features((step.pred - test.x[:, 1:].double()) / std, observed).pow(2)
    pred, _ = rollout(model, with_latent_start(model, test))
    roll = rollout_metrics(pred.double(), test.x.double(), std, test.t, horizons, features=observed)
    finite = one_step[torch.isfinite(one_step)]
    return {
        "one_step_rmse": float(finite.mean().sqrt()) if finite.numel() else math.nan,
        "rollout_rmse": roll["rmse"],
        "horizons": roll["horizons"],
        "valid_prediction_time": valid_prediction_time(
            pred.double(), test.x.double(), std, test.t, vpt_threshold, features=observed
        ),
        "n_diverged": roll["n_diverged"],
        "per_step_rmse": roll["per_step_rmse"],
    }


def with_latent_start(model: Model, data: Trajectories) -> Trajectories:
    """`data` with each record's first latent state fitted to its measured samples over the whole record (the
    model fixed); `data` itself when every state is measured or the fit fails."""
    try:
        latent = fitted_latent(model, data, data.n_times - 1)
    except DivergenceError:
        return data
    if latent is None:
        return data
    x = data.x.clone()
    x[:, 0] = latent.states(model, data)[:, 0].to(x)
    return replace(data, x=x)


def screen(model: Model, data: Trajectories, params: DiagnoseParams, seed: int) -> tuple[Diagnosis, list]:
    """The one-step screen on held-in data (its first `screen_trajectories` records), over the dynamic rows, and
    the candidate library it used."""
    data = data.subset(slice(0, params.screen_trajectories))
    rows = dynamic_rows(model, data, params.targets)
    delays = list(params.delays) if params.delays else None
    horizon = params.horizon or horizon_from_data(model, data, params.vpt_threshold)
    diag = find_effects(
        model,
        data,
        tuple(params.kinds),
        delays,
        params.n_boot,
        params.min_gain,
        params.null_factor,
        params.min_inclusion,
        seed,
        rows,
        null_segment=horizon,
    )
    diag.horizon = horizon  # the held-out windows' length too: computed once per screen
    dt = float(data.t[1] - data.t[0])
    kinds = tuple(k for k in params.kinds if k not in diag.represented + diag.not_considered)
    library = build_library(data, diag.omegas, delays or [m * dt for m in (1, 2, 4, 8)], kinds, diag.phased_omegas)
    library = with_per_node(library, diag) + drift_candidates(model, data, kinds)
    library += input_candidates(model, data, kinds)
    states = state_rows(model, data)  # a spec's `outputs:` columns are read by sensors: no effect reads them
    return diag, [c for c in library if c.source is None or c.source < states]


def white_box(model: Model) -> bool:
    """Whether every trainable parameter is a named physical parameter or an effect coefficient (then the
    multiple-shooting fit of the judgement is the whole fit, and no finetune is needed)."""
    named = {id(p) for p in own_parameters(model)} | {id(p) for p in model.effects.parameters()}
    return all(id(p) in named for p in model.parameters() if p.requires_grad)


@dataclass
class LoopResult:
    """What the loop found, did and measured."""

    diagnosis: Diagnosis  # the first screen
    judgement: Judgement  # the first held-out judgement
    verdict: str
    before: dict[str, Any]  # held-out metrics of the model as given
    after: dict[str, Any] | None = None  # ... of the model handed back (fix=true)
    rounds: list[dict[str, Any]] = field(default_factory=list)
    model: Model | None = None  # the model handed back (the given one when nothing was fixed)
    checkpoint: str | None = None  # its checkpoint (fix=true and something was added)
    rejected: list[dict[str, Any]] = field(default_factory=list)  # fixes that did not help, with their numbers
    named: list[Trial] = field(default_factory=list)  # what is named: the held-out judgement's, or the finetunes'
    finetuned: list[FinetuneJudgement] = field(default_factory=list)  # black-box fix: one comparison per round

    @property
    def exit_code(self) -> int:
        return EXIT_CODES[self.verdict]


def run_loop(
    model: Model,
    splits: Splits,
    params: DiagnoseParams,
    horizons: list[int],
    seed: int = 0,
    finetune: Finetune | None = None,
    save: Save | None = None,
    log: Callable[[str], None] = lambda _: None,
    finetune_all: FinetuneAll | None = None,
) -> LoopResult:
    """Diagnose `model` on `splits.train` (held-in), judge candidates on `splits.test` (held-out); with
    `finetune`/`save` given (fix=true), add what is named, finetune, and diagnose again, up to `params.rounds`.
    `finetune_all` runs a network's control and candidate finetunes (default: one after another with `finetune`;
    the command layer runs them in parallel processes)."""
    train, test = splits.train, splits.test
    diag, library = screen(model, train, params, seed)
    # a network absorbs part of a missing effect: with a finetune at hand its candidates are tested by finetuning
    # (diagnose/finetuned.py), and the frozen-network fits, which double-count what it absorbed, are skipped
    black_box = finetune is not None and not white_box(model)
    judgement = judge(model, diag, library, train, test, params, seed, test_candidates=not black_box)
    before = holdout_metrics(model, test, horizons, params.vpt_threshold)
    result = LoopResult(diag, judgement, judgement.verdict, before, model=model, named=judgement.named)
    if black_box and finetune is not None and judgement.verdict != NOTHING_MISSING:
        runs = finetune_all or serial(finetune)
        return _black_box_fix(model, splits, params, horizons, seed, runs, log, result, library)
    if finetune is None or save is None or judgement.verdict != EFFECTS_NAMED:
        return result
    own = [t for t in judgement.named if t.effect["_target_"].endswith(("PhasedDrive", "InputGain"))]
    if own:
        what = "phase" if own[0].effect["_target_"].endswith("PhasedDrive") else "input gain"
        result.rejected.append(
            {
                "round": 1,
                "added": [t.label for t in judgement.named],
                "why": (
                    f"{own[0].label} has its own {what} in every recording: named but not added, as a model cannot "
                    f"know the {what} of a new recording (the held-out test estimated it from a warm-up window)"
                ),
            }
        )
        return result
    result.model = _white_box_fix(model, splits, params, seed, finetune, save, log, result)
    if result.model is not model:
        result.after = _after_metrics(result.model, test, horizons, params)
    return result


def _white_box_fix(
    model: Model,
    splits: Splits,
    params: DiagnoseParams,
    seed: int,
    finetune: Finetune,
    save: Save,
    log: Callable[[str], None],
    result: LoopResult,
) -> Model:
    """fix=true with effects named by the held-out judgement: each round adds them (finetuning a model that has
    more than named parameters), keeps the better of the fits if it beats the current model on held-out data, and
    judges the kept model again. Records the rounds in `result`; returns the model handed back."""
    train, test = splits.train, splits.test
    j = result.judgement
    current, current_err = model, float(window_error(model, test, j.horizon).mean())
    for k in range(1, params.rounds + 1):
        names = [t.label for t in j.named]
        log(f"round {k}: adding {'; '.join(names)} and finetuning")
        scored = _scored_fixes(j, k, names, test, finetune)
        finite = [s for s in scored if math.isfinite(s[3])]
        if not finite:
            raise DivergenceError(
                f"the fix of round {k} ({'; '.join(names)}): every held-out rollout of the fixed "
                "model diverged (NaN/inf)."
            )
        name, best, path, err = min(finite, key=lambda s: s[3])
        entry = {
            "round": k,
            "added": names,
            "added_effects": [t.effect for t in j.named],
            "heldout_mse": {s[0]: s[3] for s in scored},
            "heldout_mse_before": current_err,
            "kept": name,
        }
        if not err < current_err:
            entry["kept"] = "nothing (rejected)"
            result.rejected.append(
                {
                    **entry,
                    "why": f"held-out multi-step MSE {current_err:.4g} → {err:.4g}: the "
                    "fix does not help, the model is returned unchanged",
                }
            )
            result.rounds.append(entry)
            break
        path = path or save(best, k)
        current, current_err, result.checkpoint = best, err, path
        entry["checkpoint"] = path
        entry["effects_after"] = [e.describe() for e in best.effects]
        log(f"round {k}: diagnosing the fixed model")
        diag_k, library_k = screen(best, train, params, seed)
        j = judge(best, diag_k, library_k, train, test, params, seed)
        entry["then"] = {"verdict": j.verdict, "named": [t.label for t in j.named]}
        result.rounds.append(entry)
        if j.verdict != EFFECTS_NAMED:
            break
    return current


def _scored_fixes(
    j: Judgement, k: int, names: list[str], test: Trajectories, finetune: Finetune
) -> list[tuple[str, Model, str | None, float]]:
    """The fixes of round `k` with their held-out multi-step MSE: (how it was fitted, model, checkpoint or None,
    MSE), the finetuned one first when the model has more than named parameters."""
    fitted = j.model
    assert fitted is not None  # a judgement that names effects carries the model they were fitted into
    options: list[tuple[str, Model, str | None]] = [("multiple-shooting fit", fitted, None)]
    if not white_box(fitted):  # a network must relearn what it made up for; a white-box fit is already done
        try:
            tuned, tuned_path = finetune(copy.deepcopy(fitted), f"round{k}")
        except DivergenceError as exc:
            raise DivergenceError(
                f"the fix of round {k} ({'; '.join(names)}) diverged while finetuning: {exc}"
            ) from None
        options.insert(0, ("finetuned", tuned, tuned_path))
    return [(name, m, path, float(window_error(m, test, j.horizon).mean())) for name, m, path in options]


def _after_metrics(model: Model, test: Trajectories, horizons: list[int], params: DiagnoseParams) -> dict[str, Any]:
    """Held-out metrics of the model handed back; raises if any of its held-out rollouts diverged."""
    after = holdout_metrics(model, test, horizons, params.vpt_threshold)
    if after["n_diverged"]:
        raise DivergenceError(
            f"the fixed model's held-out rollouts diverged on {after['n_diverged']} "
            "trajectories; it is not handed back."
        )
    return after


def _black_box_fix(
    model: Model,
    splits: Splits,
    params: DiagnoseParams,
    horizons: list[int],
    seed: int,
    finetune: FinetuneAll,
    log: Callable[[str], None],
    result: LoopResult,
    library: list[Candidate],
) -> LoopResult:
    """fix=true on a model with trainable parameters beyond its named physical ones (a network): each round
    finetunes the model without a candidate (the control) and with each screened candidate, names the best one
    that beats the control on held-out recordings (`diagnose/finetuned.py`), and screens the finetuned model
    again. The frozen-network judgement stays in the report; the verdict is the finetunes'."""
    train, test = splits.train, splits.test
    j0 = result.judgement
    current, diag, named = model, result.diagnosis, []
    for k in range(1, params.rounds + 1):
        fj = judge_by_finetune(
            current,
            diag,
            library,
            train,
            test,
            j0.horizon,
            j0.error_null,
            params,
            finetune,
            f"round{k}",
            log,
            rescreen=lambda m: screen(m, train, params, seed),
        )
        result.finetuned.append(fj)
        entry: dict[str, Any] = {
            "round": k,
            "added": [t.label for t in fj.named],
            "added_effects": [t.effect for t in fj.named],
            "heldout_mse": {"control (finetuned without a candidate)": fj.error_control}
            | {f"finetuned with {t.label}": t.error_after for t in fj.trials},
            "heldout_mse_before": fj.error_given,
            "kept": "finetuned with " + fj.named[0].label if fj.named else "nothing",
        }
        result.rounds.append(entry)
        if fj.verdict != EFFECTS_NAMED:
            break
        assert fj.model is not None
        named += fj.named
        current, result.checkpoint = fj.model, fj.checkpoint
        entry["checkpoint"] = fj.checkpoint
        entry["effects_after"] = [e.describe() for e in current.effects]
        if fj.rest is not None:  # screened already, when the judgement asked what its finetune left
            diag, library = fj.rest
        else:
            log(f"round {k}: screening the finetuned model")
            diag, library = screen(current, train, params, seed)
        left = [f.label for f in diag.findings if f.accepted]
        entry["then"] = {"verdict": "screen", "named": left}
        if not left:
            break
    if named:
        result.verdict, result.named, result.model = EFFECTS_NAMED, named, current
        result.after = _after_metrics(current, test, horizons, params)
    else:
        result.verdict, result.named = result.finetuned[0].verdict, []
    return result
