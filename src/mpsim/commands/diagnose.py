"""`mpsim diagnose init=<ckpt> (system=<name> | data.path=<file>) [fix=true]`: the residual loop.

Find the residual of a trained model on its held-in trajectories, trace it to named effects it lacks, and
with `fix=true` add them to the model (fitted initial coefficients), finetune from the checkpoint and report
the held-out error before and after. Writes diagnosis.json, diagnosis.md and plots/.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from mpsim import plotting
from mpsim.commands.common import (
    Shape,
    build,
    build_model_for,
    build_system,
    checkpoint_base,
    load_init,
    model_and_data,
    setup_runtime,
)
from mpsim.commands.console import fmt, print_summary
from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.loop import Diagnosis, Finding, find_effects, valid_prediction_time
from mpsim.diagnose.residual import one_step_residual
from mpsim.errors import ConfigError
from mpsim.files import atomic_write, write_json
from mpsim.models.base import Model
from mpsim.training.metrics import rollout_metrics
from mpsim.training.trainer import predict

log = logging.getLogger(__name__)


def holdout_metrics(model: Model, test: Trajectories, horizons: list[int], vpt_threshold: float) -> dict[str, Any]:
    """Held-out one-step error, rollout RMSE at fixed horizons and valid prediction time (normalised units)."""
    std = model.state_std.detach().cpu().double()
    step = one_step_residual(model, test)
    one_step = ((step.pred - test.x[:, 1:].double()) / std).pow(2)
    pred, _ = predict(model, test)
    roll = rollout_metrics(pred.double(), test.x.double(), std, test.t, horizons)
    return {
        "one_step_rmse": float(one_step[torch.isfinite(one_step)].mean().sqrt()),
        "rollout_rmse": roll["rmse"],
        "horizons": roll["horizons"],
        "valid_prediction_time": valid_prediction_time(pred.double(), test.x.double(), std, test.t, vpt_threshold),
        "n_diverged": roll["n_diverged"],
        "per_step_rmse": roll["per_step_rmse"],
    }


def _true_effects(cfg: DictConfig) -> list[dict[str, Any]]:
    """The effects the simulated data were made with (used only to score the result, never to find it)."""
    if cfg.data.path or "effects" not in cfg.system:
        return []
    return list(OmegaConf.to_container(cfg.system.effects, resolve=True) or [])


def _compare(found: dict[str, Any], truths: list[dict[str, Any]]) -> dict[str, Any] | None:
    """Relative error of a found effect's parameters against the true effect of the same kind and target."""
    for true in truths:
        if true.get("_target_", "").split(".")[-1] != found["_target_"].split(".")[-1]:
            continue
        if true.get("target") != found.get("target"):
            continue
        keys = ("amplitude", "omega") if "omega" in found else ("coef",)
        out = {"true": {k: true.get(k) for k in keys}}
        out["relative_error"] = {
            k: abs(found[k] - true[k]) / abs(true[k]) for k in keys if isinstance(true.get(k), int | float) and true[k]
        }
        return out
    return None


def run_diagnose(cfg: DictConfig, output_dir: str | Path | None = None, overrides: list[str] | None = None) -> dict:
    """Diagnose `init=` on held-in data; with `fix=true` also add, finetune and compare on held-out data."""
    rt = setup_runtime(cfg, output_dir, overrides)
    if not cfg.init:
        raise ConfigError("mpsim diagnose needs init=<checkpoint> (the trained model to diagnose).")
    ckpt = load_init(cfg, rt)
    system = None if cfg.data.path and cfg.data.graph != "system" else build_system(cfg)
    model, model_cfg, splits = model_and_data(cfg, rt, system, ckpt, refit=False)
    model.latent_reset = cfg.trainer.window  # latent states (messages) were trained over windows this long
    p = cfg.diagnose
    horizons = list(cfg.eval.horizons)
    log.info(f"diagnosing {Path(ckpt['path']).name} on {len(splits.train)} held-in trajectories")
    diag = find_effects(model, splits.train, tuple(p.kinds), list(p.delays) if p.delays else None, p.n_boot,
                        p.min_gain, p.null_factor, p.min_inclusion, cfg.seed)
    before = holdout_metrics(model, splits.test, horizons, p.vpt_threshold)
    truths = _true_effects(cfg)
    found = []
    for f in diag.accepted:
        found.append({**f.as_dict(), "vs_truth": _compare(f.effect, truths)})
    result: dict[str, Any] = {
        "task": "diagnose",
        "init": ckpt["path"],
        "data": {"name": splits.train.system_name, "source": cfg.data.path or "simulated",
                 "n_heldin": len(splits.train), "n_heldout": len(splits.test)},
        "verdict": "effects found" if diag.accepted else "no effect found",
        "effects_found": found,
        "diagnosis": diag.as_dict(),
        "before": before,
        "true_effects": truths,
    }
    if cfg.fix and diag.accepted:
        final = _fix_in_rounds(cfg, rt, ckpt, model_cfg, model, splits, diag, horizons, truths)
        result.update(final)
        result["verdict"] = "effects found" if result["effects_named"] else "no effect found"
    elif cfg.fix:
        result["after"] = None
    _plots(diag, before, result.get("after"), splits.test, rt.output_dir)
    write_json(rt.output_dir / "diagnosis.json", result)
    text = _markdown(result, diag)
    atomic_write(rt.output_dir / "diagnosis.md", lambda f: f.write(text), mode="w")
    _print(result, diag, rt.output_dir)
    return result


def strongest(diag: Diagnosis) -> Finding:
    """The accepted finding that stands furthest above its null threshold (the one a round adds)."""
    return max(diag.accepted, key=lambda f: f.explained_rms / max(f.threshold, 1e-300))


def _fix_in_rounds(cfg, rt, ckpt, model_cfg, model, splits, diag: Diagnosis, horizons, truths) -> dict[str, Any]:
    """Add the effects one at a time: the strongest finding, finetune, diagnose the finetuned model again.

    A one-shot fit can name a term that only compensates for what the model did to make up for the main
    effect (an MP-NODE without a clock that learned part of a drive on x leaves a drive-like residual on y):
    once the main effect is part of the model and the weights are refit, such a term is gone from the residual
    and is never added. The loop stops when a diagnosis names nothing or after `diagnose.rounds` rounds.
    """
    p = cfg.diagnose
    rounds: list[dict[str, Any]] = []
    current, current_cfg, current_ckpt, current_diag = model, model_cfg, ckpt, diag
    while current_diag.accepted and len(rounds) < p.rounds:
        k = len(rounds) + 1
        add = strongest(current_diag)
        log.info(f"round {k}: adding {add.label} and finetuning")
        run_dir = rt.output_dir / "fix" / f"round{k}"
        fixed, after, fixed_cfg = _fix(cfg, rt, current_ckpt, current_cfg, current, splits, add,
                                       current_diag.parameter_shifts, horizons, run_dir)
        log.info(f"round {k}: diagnosing the finetuned model")
        again = find_effects(fixed, splits.train, tuple(p.kinds), list(p.delays) if p.delays else None, p.n_boot,
                             p.min_gain, p.null_factor, p.min_inclusion, cfg.seed)
        rounds.append({
            "round": k,
            "added": add.label,
            "added_effect": add.effect,
            "found_before": [f.label for f in current_diag.accepted],
            "effects_after_finetune": [e.describe() for e in fixed.effects],
            "after": {key: after[key] for key in ("one_step_rmse", "rollout_rmse", "valid_prediction_time")},
            "then_found": [f.label for f in again.accepted],
            "then_found_detail": [f.as_dict() for f in again.accepted],
        })
        current_ckpt = {**current_ckpt, "path": str(run_dir / "checkpoints" / "best.ckpt"),
                        "model": {**current_ckpt["model"], "config": fixed_cfg, "state_dict": fixed.state_dict()}}
        current, current_cfg, current_diag = fixed, fixed_cfg, again
    named = [r["added"] for r in rounds]
    dropped = [f.label for f in diag.accepted if f.label not in named]
    return {
        "rounds": rounds,
        "effects_named": named,
        "not_confirmed": dropped,  # found in the first diagnosis, gone once the stronger effects were added
        "still_found": [f.label for f in current_diag.accepted],  # non-empty only when the rounds ran out
        "after": after,
        "fixed_model_config": current_cfg,
        "fixed_effects": [{"effect": e.config(), "describe": e.describe(), "vs_truth": _compare(e.config(), truths)}
                          for e in current.effects],
        "fixed_checkpoint": current_ckpt["path"],
    }


def _fix(cfg, rt, ckpt, model_cfg, model, splits, add: Finding, shifts: dict[str, float], horizons, run_dir: Path):
    """Add one effect to the model config, finetune from the checkpoint, evaluate held-out."""
    fixed_cfg = dict(model_cfg)
    fixed_cfg["effects"] = list(model_cfg.get("effects") or []) + [add.effect]
    fixed_ckpt = {**ckpt, "model": {**ckpt["model"], "config": fixed_cfg}}
    fixed, _ = build_model_for(cfg, rt, Shape.of(splits.train), fixed_ckpt)
    fixed.set_normalisation(model.state_mean, model.state_std)
    fixed.shift_parameters(shifts)  # the joint refit of the model's own parameters
    fixed.latent_reset = model.latent_reset
    # the finetune starts near the optimum (fitted coefficients, trained weights): smaller steps
    trainer = build(cfg.trainer, "trainer", lr=cfg.trainer.lr * cfg.diagnose.fix_lr_factor)
    base = checkpoint_base(fixed_cfg, fixed, splits.train.meta, {"mode": "finetune", "init": ckpt["path"]})
    trainer.fit(fixed, splits.train, splits.val, splits.test, run_dir=run_dir, seed=cfg.seed, checkpoint_base=base)
    after = holdout_metrics(fixed, splits.test, horizons, cfg.diagnose.vpt_threshold)
    after["epochs"] = trainer.history_[-1]["epoch"]
    return fixed, after, fixed_cfg


def _plots(diag: Diagnosis, before, after, test: Trajectories, out: Path) -> None:
    res = diag.residual
    if res is None:
        return
    plotting.residuals(res.t_mid, res.r, diag.state_names, out / "plots" / "residual.png")
    if diag.periodograms:
        plotting.periodograms(diag.periodograms, diag.state_names, out / "plots" / "periodogram.png")
    plotting.explained_variance(diag.explained, diag.state_names, out / "plots" / "explained_variance.png")
    curves = {"before": before["per_step_rmse"]}
    if after:
        curves["after"] = after["per_step_rmse"]
    plotting.error_curves(test.t, curves, out / "plots" / "before_after.png")


def _markdown(result: dict[str, Any], diag: Diagnosis) -> str:
    names = diag.state_names
    lines = [f"# mpsim diagnose: {result['data']['name']}", "", f"Model: `{result['init']}`. "
             f"Held-in trajectories: {result['data']['n_heldin']}; held-out: {result['data']['n_heldout']}.", "",
             f"**Verdict: {result['verdict']}.**", ""]
    lines += ["Residuals are in raw units per unit time, after refitting the model's own parameters (white-box "
              "models). The null data are the model's own rollouts plus the noise level estimated from the data; "
              "the null level is the largest part of their residual (RMS) any candidate explains.", "",
              "| state | residual RMS | null residual RMS | null level | estimated noise |", "|---|---|---|---|---|"]
    for d, n in enumerate(names):
        lines.append(f"| {n} | {diag.residual_rms[d]:.4g} | {diag.null_rms[d]:.4g} | {diag.null_level[d]:.3g} | "
                     f"{diag.noise_std[d]:.3g} |")
    if diag.represented:
        lines += ["", f"Effect kinds the model can express itself ({', '.join(diag.represented)}) and polynomials of a "
                      "node's state were refit as nuisance directions, not named: the model's residual along them is "
                      "training error, not missing physics."]
    if diag.not_considered:
        lines += ["", f"Not considered: {', '.join(diag.not_considered)} — against this model such a term cannot be "
                      "told apart from its own error (see the model class's `indistinguishable`)."]
    if diag.parameter_shifts:
        lines += ["", "Refit of the model's own parameters alongside the named effects: "
                  + ", ".join(f"{k} {v:+.4g}" for k, v in diag.parameter_shifts.items()) + "."]
    lines += ["", "## Candidates selected by BIC", "",
              "Coefficients of named effects are refit jointly with the other named effects; intervals come from "
              "the bootstrap of the selection fit.", "",
              "| target: effect | coefficients | 95% interval | residual explained | RMS explained | bootstrap | "
              "named | why |", "|---|---|---|---|---|---|---|---|"]
    for f in diag.findings:
        coef = ", ".join(f"{c:.4g}" for c in f.coef)
        ci = ", ".join(f"[{a:.4g}, {b:.4g}]" for a, b in f.interval)
        lines.append(f"| {f.label} | {coef} | {ci} | {f.gain:.1%} | {f.explained_rms:.3g} | {f.inclusion:.0%} | "
                     f"{'yes' if f.accepted else 'no'} | {f.reason} |")
    if not diag.findings:
        lines.append("| (none: no candidate lowered the BIC) | | | | | | | |")
    if result.get("rounds"):
        lines += ["", "## Rounds (fix=true): add the strongest finding, finetune, diagnose again", "",
                  "| round | found | added | effects after finetune | one-step RMSE | rollout RMSE | then found |",
                  "|---|---|---|---|---|---|---|"]
        for r in result["rounds"]:
            a = r["after"]
            lines.append(f"| {r['round']} | {'; '.join(r['found_before'])} | {r['added']} | "
                         f"{'; '.join(r['effects_after_finetune'])} | {fmt(a['one_step_rmse'])} | "
                         f"{fmt(a['rollout_rmse'])} | {'; '.join(r['then_found']) or 'nothing'} |")
        if result["not_confirmed"]:
            lines += ["", f"Not confirmed: {'; '.join(result['not_confirmed'])} — found in the first diagnosis but not "
                          "once the stronger effects were part of the model and its weights refit (the model's "
                          "compensation for them, not an effect of its own). Not added."]
        if result["still_found"]:
            lines += ["", f"Still found after {len(result['rounds'])} rounds (diagnose.rounds): "
                          f"{'; '.join(result['still_found'])}. Not added; raise diagnose.rounds to continue."]
    if result.get("fixed_effects"):
        lines += ["", "## After adding the effects and finetuning", ""]
        for e in result["fixed_effects"]:
            truth = e["vs_truth"]
            extra = f" ({_truth_text(truth)})" if truth else ""
            lines.append(f"- {e['describe']}{extra}")
    lines += ["", "## Held-out error (normalised units)", "", "| | before | after |", "|---|---|---|"]
    before, after = result["before"], result.get("after") or {}
    rows = [("one-step RMSE", "one_step_rmse"), ("rollout RMSE (full horizon)", "rollout_rmse"),
            ("valid prediction time", "valid_prediction_time")]
    for label, key in rows:
        lines.append(f"| {label} | {fmt(before[key])} | {fmt(after.get(key))} |")
    for h, v in before["horizons"].items():
        a = (after.get("horizons") or {}).get(h, {}).get("rmse")
        lines.append(f"| rollout RMSE at {h} steps (t={v['t']:.3g}) | {fmt(v['rmse'])} | {fmt(a)} |")
    return "\n".join(lines) + "\n"


def _truth_text(truth: dict[str, Any]) -> str:
    return ", ".join(f"true {k} {truth['true'][k]:.4g}, off by {v:.1%}" for k, v in truth["relative_error"].items())


def _print(result: dict[str, Any], diag: Diagnosis, out: Path) -> None:
    rows = [("verdict", result["verdict"])]
    for f in diag.accepted:
        ci = ", ".join(f"[{a:.3g}, {b:.3g}]" for a, b in f.interval)
        rows.append(("effect", f"{f.label}: coef {', '.join(f'{c:.4g}' for c in f.coef)} (bootstrap 95% of its single-variable fit {ci}), explains "
                               f"{f.gain:.0%} of the residual"))
        if f.kind == "PeriodicForcing":
            rows.append(("", f"{f.effect['amplitude']:.4g}·sin({f.effect['omega']:.4g} t {f.effect['phase']:+.3f})"))
    if not diag.accepted:
        best = max(diag.findings, key=lambda f: f.gain, default=None)
        why = f"best candidate {best.label}: {best.reason}" if best else "no candidate lowered the BIC"
        rows.append(("why", why))
        rows.append(("residual RMS", ", ".join(f"{n} {r:.3g} (null {q:.3g})" for n, r, q in
                                               zip(diag.state_names, diag.residual_rms, diag.null_rms, strict=True))))
    for r in result.get("rounds", []):
        rows.append((f"round {r['round']}", f"added {r['added']}; then found: {'; '.join(r['then_found']) or 'nothing'}"))
    if result.get("not_confirmed"):
        rows.append(("not confirmed", "; ".join(result["not_confirmed"])))
    for e in result.get("fixed_effects", []):
        truth = e["vs_truth"]
        rows.append(("after finetune", e["describe"] + (f"  ({_truth_text(truth)})" if truth else "")))
    before, after = result["before"], result.get("after")
    for label, key in (("one-step RMSE", "one_step_rmse"), ("rollout RMSE", "rollout_rmse"),
                       ("valid pred. time", "valid_prediction_time")):
        rows.append((label, f"{fmt(before[key])}" + (f" → {fmt(after[key])}" if after else "")))
    rows.append(("report", str(out / "diagnosis.md")))
    print_summary(f"mpsim diagnose: {result['data']['name']}", rows)

