"""The diagnosis report: diagnosis.md, the one-screen summary and the plots of `mpsim diagnose`.

Plain values in: the summary dict the command writes as diagnosis.json (`markdown`, `summary_rows`), or the
loop's result for the plots, which need its tensors (`plots`).
"""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import torch

from mpsim import plotting
from mpsim.console import fmt
from mpsim.data.account import record_lines
from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.heldout import EFFECTS_NAMED, NOTHING_MISSING
from mpsim.diagnose.loop import LoopResult
from mpsim.diagnose.nuisance import INPUT_KINDS
from mpsim.diagnose.residual import one_step_residual
from mpsim.effects.base import EffectContext
from mpsim.errors import DivergenceError


def plots(result: LoopResult, t: torch.Tensor, out: Path) -> None:  # t: [T] held-out time grid
    """Residual, periodogram, explained-variance and before/after error plots under `out`/plots."""
    diag = result.diagnosis
    res = diag.residual
    if res is None:
        return
    plotting.residuals(res.t_mid, res.r, diag.state_names, out / "plots" / "residual.png")
    if diag.periodograms:
        plotting.periodograms(diag.periodograms, diag.state_names, out / "plots" / "periodogram.png")
    plotting.explained_variance(diag.explained, diag.state_names, out / "plots" / "explained_variance.png")
    curves = {"before": result.before["per_step_rmse"]}
    if result.after:
        curves["after"] = result.after["per_step_rmse"]
    plotting.error_curves(t, curves, out / "plots" / "before_after.png")


def feature_plots(result: LoopResult, data: Trajectories, out: Path) -> list[Path]:
    """plots/effect_<k>.png per named effect with a source state: the partial residual — the one-step residual of
    the fitted model (every named effect in it, its own parameters refit) on the effect's row of `data` (held-out
    records; latent states at their estimate), plus this effect's term — against the effect's source state,
    binned, beside the fitted term (`plotting.effect_against_feature`). Where the effect is right the bins follow
    the term; a model as given would show it mixed with what its own parameters absorbed. None for a named effect of time
    alone (a drive, a drift) or a constant (a bias: nothing to plot it against)."""
    model = result.model if result.after is not None and result.model is not None else result.judgement.model
    named = result.named
    if model is None or not named or len(model.effects) < len(named):
        return []
    effects = list(model.effects)[-len(named) :]
    try:
        res = one_step_residual(model, data)  # the fitted model, every named effect in it
    except DivergenceError:
        return []
    x = data.x[:, :-1].double()  # [B, T-1, N, D] the states each step starts from
    b, steps, n, d = x.shape
    flat = x.reshape(b * steps, n, d)
    edges = data.edge_index if data.shared_graph else data.edge_index.repeat_interleave(steps, dim=0)
    ctx = EffectContext.for_batch(edges, flat)
    names, paths = data.state_names, []
    for k, (trial, effect) in enumerate(zip(named, effects, strict=True), start=1):  # the few named effects
        source, target = getattr(effect, "source", None), getattr(effect, "target", None)
        if (
            source is None
            or target is None
            or trial.kind in ("Bias", "PeriodicForcing", "ParameterDrift", *INPUT_KINDS)
        ):
            continue
        with torch.no_grad():
            term = copy.deepcopy(effect).double()(torch.zeros((), dtype=torch.float64), flat, ctx)[..., target]
        term = term.reshape(-1)
        paths.append(
            plotting.effect_against_feature(
                x[..., source].reshape(-1),
                res.r[..., target].double().reshape(-1) + term,  # the partial residual: what is left, plus the effect
                term,
                f"{names[source]} (the effect's source)",
                f"d{names[target]}/dt: residual + the effect's term",
                out / "plots" / f"effect_{k}.png",
                title=trial.label,
            )
        )
    return paths


def values_text(values: dict[str, float], interval: dict[str, Any]) -> str:
    """Fitted values with their 95 % intervals: "coef 0.2 [0.19, 0.21], ..."."""
    return ", ".join(f"{k} {v:.4g} [{interval[k][0]:.4g}, {interval[k][1]:.4g}]" for k, v in values.items())


def truth_text(truth: dict[str, Any]) -> str:
    """A found effect's relative error against the true one: "true coef 0.2, off by 1.0%, ..."."""
    return ", ".join(f"true {k} {truth['true'][k]:.4g}, off by {v:.1%}" for k, v in truth["relative_error"].items())


def markdown(s: dict[str, Any]) -> str:
    """diagnosis.md from the summary dict `s` (diagnosis.json's content)."""
    lines = _verdict_section(s) + _free_run_section(s.get("freerun"))
    if s.get("feature_plots"):
        lines += [
            "",
            "Each named effect's partial residual (the fitted model's residual plus the effect's term) against the "
            "effect's own feature, beside the fitted term: " + ", ".join(f"![{p}]({p})" for p in s["feature_plots"]),
        ]
    lines += _heldout_section(s["judgement"])
    for k, f in enumerate(s["finetuned"], start=1):
        lines += _finetuned_section(k, f)
    lines += _screen_section(s["screen"]) + _fix_section(s) + _error_table(s["before"], s["after"] or {})
    return "\n".join(lines) + "\n"


def _verdict_section(s: dict[str, Any]) -> list[str]:
    """Title, data, verdict, how to read it, and the held-out levels of the judgement."""
    j = s["judgement"]
    lines = [
        f"# mpsim diagnose: {s['data']['name']}",
        "",
        f"Model: `{s['init']}`. Held-in trajectories: {s['data']['n_heldin']}; held-out: {s['data']['n_heldout']}.",
        "",
        f"**Verdict: {s['verdict']}** (exit code {s['exit_code']}). {s['verdict_note']}",
        "",
        "## How to read the verdict",
        "",
        "- *effects named*: each named effect, fitted by multiple shooting through the model's own integrator, "
        "lowered the held-out multi-step error by more than the same fit does on null data, and together they "
        "remove most of the error above the null level.",
        "- *nothing missing*: the model (its own parameters refit) predicts held-out data at the null level.",
        "- *unexplained structured residual*: the error is above the null level and no candidate explains it; "
        "nothing is claimed (the best candidate and what it would leave are shown).",
        "- With `fix=true` and a model that has a network, a candidate is named only if the model finetuned with "
        "it beats the same finetune without it (the control) on held-out recordings, and removes most of the "
        "control's error above the null level.",
        "",
        "## Held-out multi-step error (MSE, normalised)",
        "",
        f"Windows of {j['horizon']} steps. Model as given {j['error_given']:.4g}; its own parameters refit "
        f"{j['error_refit']:.4g}; null level {j['error_null']:.4g}; with the named effects {j['error_final']:.4g} "
        f"(share of the excess removed: {j['explained']:.0%}).",
        "",
    ]
    return lines + [f"- {n}" for n in j["notes"]] + _data_section(s["data"])


def _free_run_section(free: dict[str, Any] | None) -> list[str]:
    """The held-out records free-run by the model as given and by the model handed back (raw units)."""
    if not free or not free.get("rows"):
        return []
    after = any("after_rmse" in r for r in free["rows"])
    start = "eval.init_samples" if free.get("init_samples_given") else "what the latent states need"
    lines = [
        "",
        "## Free run of the held-out records (RMSE in the signal's units)",
        "",
        f"Each held-out record simulated whole from its first {free['init_samples']} samples ({start}), open loop "
        "with its measured input; scored after those samples. "
        + (
            "Before: the model as given; after: the model handed back with the named effects."
            if after
            else "The model as given (no fix was returned)."
        ),
        "",
        "| record | channel | RMSE before | fit before | " + ("RMSE after | fit after |" if after else ""),
        "|---|---|---|---|" + ("---|---|" if after else ""),
    ]
    for r in free["rows"]:  # the few held-out records and channels
        name = Path(str(r["record"])).name + (f" from {r['t0']:.4g} s" if isinstance(r.get("t0"), int | float) else "")
        cells = [name, r["channel"], fmt(r["before_rmse"]), f"{r['before_fit']:.1f} %"]
        if after:
            cells += [fmt(r.get("after_rmse", math.nan)), f"{r.get('after_fit', math.nan):.1f} %"]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _data_section(data: dict[str, Any]) -> list[str]:
    """What was read from the file: every file's rows, gaps, pieces left out, and what each split covers."""
    bullets = record_lines(data)
    return ["", "## Data", "", *bullets] if bullets else []


def _null_text(gain: Any) -> str:
    """A trial's null gain; none when the candidate failed on the data and was not fitted to null data."""
    return f"{gain:.3g}" if isinstance(gain, int | float) and math.isfinite(gain) else "not fitted (failed on the data)"


def _heldout_section(j: dict[str, Any]) -> list[str]:
    """The candidates the held-out judgement `j` tested, one table row each."""
    lines = [
        "",
        "## Candidates tested on held-out data",
        "",
        "| effect | fitted (95 % interval) | held-out MSE before → after | gain ± se | null gain | test | named | why |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for t in j["trials"]:
        lines.append(
            f"| {t['label']} | {values_text(t['values'], t['interval'])} | {t['error_before']:.4g} → "
            f"{t['error_after']:.4g} | {t['gain']:.3g} ± {t['gain_se']:.2g} | {_null_text(t.get('null_gain'))} | "
            f"{t.get('test') or '—'} | {'yes' if t['accepted'] else 'no'} | {t['reason']} |"
        )
    if not j["trials"]:
        lines.append("| (none tested) | | | | | | | |")
    return lines + [f"- {t['label']}: {t['derived']}" for t in j["trials"] if t.get("derived")]


def _finetuned_section(k: int, f: dict[str, Any]) -> list[str]:
    """Round `k` of a network's candidates judged by finetuning (`f`: its judgement)."""
    lines = [
        "",
        f"## Candidates finetuned with the network (fix, round {k})",
        "",
        "The model has trainable parameters beyond its named physical ones, so each screened candidate is added "
        "and the model finetuned, against the same finetune without a candidate (the control). "
        f"Held-out MSE over {f['horizon']}-step windows: model as given {f['error_given']:.4g}; "
        + (f"control {f['error_control']:.4g}; " if f["trials"] else "no control (nothing to compare); ")
        + f"null level {f['error_null']:.4g}; verdict of this round: {f['verdict']}"
        + (f" (share of the control's excess removed: {f['explained']:.0%})." if f["named"] else "."),
        "",
        "| effect | finetuned value (95 % interval) | held-out MSE control → with it | gain ± se | test | named | why |",
        "|---|---|---|---|---|---|---|",
    ]
    for t in f["trials"]:
        lines.append(
            f"| {t['label']} | {values_text(t['values'], t['interval'])} | {t['error_before']:.4g} → "
            f"{t['error_after']:.4g} | {t['gain']:.3g} ± {t['gain_se']:.2g} | {t.get('test') or '—'} | "
            f"{'yes' if t['accepted'] else 'no'} | {t['reason']} |"
        )
    return lines + [f"- {n}" for n in f["notes"]]


def _screen_section(screen: dict[str, Any]) -> list[str]:
    """The one-step screen: residual levels per state, then every candidate it considered."""
    lines = [
        "",
        "## One-step screen",
        "",
        f"Rows searched: {', '.join(screen['searched_rows'])} (kinematic rows are "
        "not searched unless `diagnose.targets` names them).",
        "",
        *[f"- {note}" for note in screen.get("equivalent_forms", [])],
        *([""] if screen.get("equivalent_forms") else []),
        *[f"- {note}" for note in screen.get("per_node", [])],
        *([""] if screen.get("per_node") else []),
        "| state | residual RMS | null residual RMS | null level | estimated noise |",
        "|---|---|---|---|---|",
    ]
    for d, n in enumerate(screen["state_names"]):
        lines.append(
            f"| {n} | {screen['residual_rms'][d]:.4g} | {screen['null_rms'][d]:.4g} | "
            f"{screen['null_level'][d]:.3g} | {screen['noise_std_estimate'][d]:.3g} |"
        )
    lines += [
        "",
        "| target: effect | one-step coefficients | share of its row | bootstrap | screened | why |",
        "|---|---|---|---|---|---|",
    ]
    for f in screen["candidates_considered"]:
        chosen = f.get("selected", True)  # False: the best of a kind the joint fit did not select, fitted alone
        lines.append(
            f"| {f['label']}{'' if chosen else ' (best of its kind)'} | {', '.join(f'{c:.4g}' for c in f['coef'])}"
            f"{'' if chosen else ' (alone)'} | {f['gain']:.1%}{'' if chosen else ' alone'} | "
            f"{f['inclusion']:.0%} | {'yes' if f['accepted'] else 'no'} | {f['reason']} |"
        )
    if any(not f.get("selected", True) for f in screen["candidates_considered"]):
        lines += [
            "",
            "Rows marked *best of its kind* were not selected by the joint fit: each is the candidate of its kind "
            "that explains most of its row on its own (share and coefficients fitted alone), listed so that the "
            "held-out judgement can test every kind, not only the one the one-step fit preferred.",
        ]
    if any((f.get("effect") or {}).get("harmonic", 1) > 1 for f in screen["candidates_considered"]):
        lines += [
            "",
            "k = 2, 3 in a coupling's name: its second or third harmonic, Σ_j sin(k(θ_j − θ_i)) (cos likewise); "
            "each harmonic counts as a kind of its own.",
        ]
    return lines


def _fix_section(s: dict[str, Any]) -> list[str]:
    """The rounds of fix=true, the fixes rejected, and the effects of the returned model."""
    lines: list[str] = []
    for r in s["rounds"]:
        lines += [
            "",
            f"## Fix, round {r['round']}",
            "",
            f"Added {'; '.join(r['added'])}; held-out MSE before {r['heldout_mse_before']:.4g}, "
            + ", ".join(f"{k} {v:.4g}" for k, v in r["heldout_mse"].items())
            + f"; kept: {r['kept']}.",
        ]
        if "then" in r:
            lines.append(f"Then: {r['then']['verdict']} ({'; '.join(r['then']['named']) or 'nothing named'}).")
    for r in s["rejected_fixes"]:
        lines += ["", f"Rejected fix (round {r['round']}): {r['why']}."]
    if s["fixed_effects"]:
        lines += ["", "## Effects in the returned model", ""]
        lines += [
            f"- {e['describe']}" + (f" ({truth_text(e['vs_truth'])})" if e["vs_truth"] else "")
            for e in s["fixed_effects"]
        ]
        lines.append(f"- checkpoint: `{s['fixed_checkpoint']}`")
        spec = s.get("fixed_spec")
        if spec:
            lines.append(
                f"- as equations: `{spec['path']}` (`mpsim train model=equations model.spec={spec['path']}`)"
                + (
                    f"; read back, its held-out MSE {spec['heldout_mse']:.4g} (the fixed model's "
                    f"{spec['fixed_model_heldout_mse']:.4g})"
                    if "heldout_mse" in spec
                    else f"; it does not read back: {spec.get('read_back_error')}"
                )
            )
            lines += [f"- not written into it (carry as model.effects): {why}" for why in spec["left_out"]]
    return lines


def _error_table(before: dict[str, Any], after: dict[str, Any]) -> list[str]:
    """Held-out error of the model as given and as returned ({} when nothing was returned)."""
    lines = ["", "## Held-out error (normalised)", "", "| | before | after |", "|---|---|---|"]
    for label, key in (
        ("one-step RMSE", "one_step_rmse"),
        ("rollout RMSE (full horizon)", "rollout_rmse"),
        ("valid prediction time", "valid_prediction_time"),
    ):
        lines.append(f"| {label} | {fmt(before[key])} | {fmt(after.get(key))} |")
    for h, v in before["horizons"].items():
        a = (after.get("horizons") or {}).get(h, {}).get("rmse")
        lines.append(f"| rollout RMSE at {h} steps (t={v['t']:.3g}) | {fmt(v['rmse'])} | {fmt(a)} |")
    return lines


def summary_rows(s: dict[str, Any], out: Path) -> list[tuple[str, str]]:
    """The (label, value) rows of the one-screen summary of the summary dict `s`; `out`: the run folder."""
    rows = [("verdict", s["verdict"] + (f" ({s['verdict_note']})" if s["verdict_note"] else ""))]
    for t in s["effects_named"]:
        truth = f"  ({truth_text(t['vs_truth'])})" if t.get("vs_truth") else ""
        rows.append(("effect", f"{t['label']}: {values_text(t['values'], t['interval'])}{truth}"))
        if t.get("test"):
            rows.append(("", t["test"]))
        if t.get("derived"):
            rows.append(("", t["derived"]))
    for r in (s.get("freerun") or {}).get("rows", []):
        after = f" → {fmt(r['after_rmse'])}" if "after_rmse" in r else ""
        rows.append(("free run", f"{Path(str(r['record'])).name} {r['channel']}: RMSE {fmt(r['before_rmse'])}{after}"))
    rows += _level_rows(s)
    if s["verdict"] != EFFECTS_NAMED and s["verdict"] != NOTHING_MISSING:
        rows.append(("claim", "none: no candidate explains the structured residual"))
    for r in s["rounds"]:
        rows.append((f"round {r['round']}", f"added {'; '.join(r['added'])}; kept {r['kept']}"))
    for e in s["fixed_effects"]:
        rows.append(("returned model", e["describe"] + (f"  ({truth_text(e['vs_truth'])})" if e["vs_truth"] else "")))
    before, after = s["before"], s["after"]
    for label, key in (
        ("one-step RMSE", "one_step_rmse"),
        ("rollout RMSE", "rollout_rmse"),
        ("valid pred. time", "valid_prediction_time"),
    ):
        value = before[key]
        rows.append(
            (
                label,
                f"{fmt(value)}"
                + (f" → {fmt(after[key])}" if after else "")
                + ("" if math.isfinite(value) else " (diverged)"),
            )
        )
    rows.append(("report", str(out / "diagnosis.md")))
    return rows


def _level_rows(s: dict[str, Any]) -> list[tuple[str, str]]:
    """The held-out levels: the finetunes' round by round (a network's candidates), else the judgement's."""
    rows: list[tuple[str, str]] = []
    if s["finetuned"]:  # a network's candidates were judged by finetuning: its numbers, round by round
        for k, f in enumerate(s["finetuned"], start=1):
            rows.append(
                (
                    f"held-out MSE ({k})",
                    f"given {f['error_given']:.3g}, "
                    + (f"control (finetuned without a candidate) {f['error_control']:.3g}, " if f["trials"] else "")
                    + f"null level {f['error_null']:.3g}"
                    + (f", finetuned with the effect {f['error_final']:.3g}" if f["named"] else ""),
                )
            )
            rows += [("", note) for note in f["notes"]]
        return rows
    j = s["judgement"]
    rows.append(
        (
            "held-out MSE",
            f"given {j['error_given']:.3g}, own parameters refit {j['error_refit']:.3g}, null "
            f"level {j['error_null']:.3g}"
            + (f", with the effects {j['error_final']:.3g}" if s["verdict"] == EFFECTS_NAMED else ""),
        )
    )
    return rows + [("", note) for note in j["notes"]]
