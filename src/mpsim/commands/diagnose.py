"""`mpsim diagnose init=<ckpt> (system=<name> | data.path=<file>) [fix=true]`: the residual loop.

A thin shell around `mpsim.diagnose.loop.run_loop`: read the config, build the model and the splits, supply
the finetune (a trainer run under fix/round<k>/), and write diagnosis.json, diagnosis.md and plots/ (their text
and figures: `mpsim.diagnose.report`). The verdict sets the exit code: 0 effects named, 10 nothing missing, 11
unexplained structured residual (errors keep theirs: 2 bad input, 3 a diverged fix, ...).
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import torch
import yaml
from omegaconf import DictConfig

from mpsim import plotting
from mpsim.commands.building import Shape, build, build_model_for
from mpsim.commands.prepare import Job, prepare
from mpsim.commands.runtime import Runtime
from mpsim.commands.scoring import EvalOptions, eval_options
from mpsim.config import plain_dict
from mpsim.console import print_summary
from mpsim.data.account import data_record
from mpsim.data.dataset import Splits
from mpsim.diagnose import report
from mpsim.diagnose.finetuned import serial
from mpsim.diagnose.fixed import written_spec
from mpsim.diagnose.heldout import EFFECTS_NAMED, NOTHING_MISSING, UNEXPLAINED
from mpsim.diagnose.loop import LoopResult, holdout_metrics, run_loop
from mpsim.diagnose.params import DiagnoseParams
from mpsim.diagnose.shooting import null_data, window_error
from mpsim.errors import ConfigError, DataError, DivergenceError
from mpsim.files import atomic_write, write_json
from mpsim.models.base import Model
from mpsim.models.capabilities import LatentState
from mpsim.models.equations import EquationsModel
from mpsim.models.freerun import free_run, summary_of
from mpsim.solvers.odeint import ODESolver
from mpsim.training.checkpoint import checkpoint_base, save_checkpoint

log = logging.getLogger(__name__)

__all__ = ["holdout_metrics", "run_diagnose"]


def true_effects(job: Job) -> list[dict[str, Any]]:
    """The effects the simulated data were made with (used only to score the result, never to find it)."""
    if job.data.from_file:
        return []
    return list(job.system_config.get("effects") or [])


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
            k: abs(found[k] - true[k]) / abs(true[k])
            for k in keys
            if isinstance(true.get(k), int | float) and isinstance(found.get(k), int | float) and true[k]
        }
        return out
    return None


def run_diagnose(cfg: DictConfig, output_dir: str | Path | None = None, overrides: list[str] | None = None) -> dict:
    """Diagnose `init=` on held-in data, judge on held-out data; with `fix=true` also add, finetune, compare."""
    params = DiagnoseParams(**plain_dict(cfg.diagnose))  # settings are checked before anything is read or built
    if not cfg.init:
        raise ConfigError("mpsim diagnose needs init=<checkpoint> (the trained model to diagnose).")
    if not cfg.data.path:  # simulated: its held-out count is known before anything is simulated
        check_heldout(int(cfg.data.n_test))
    job = prepare(cfg, "diagnose", output_dir, overrides, training=bool(cfg.fix))
    model, splits, ckpt = job.model, job.splits, job.checkpoint
    assert model is not None and splits is not None and ckpt is not None  # prepared with init= and data
    if job.data.official:  # a benchmark's split: its test part is what it is
        check_heldout_records(len(splits.test))
    else:
        check_heldout(len(splits.test), sum(splits.sizes().values()), list(cfg.data.split) if cfg.data.path else None)
    if isinstance(model, LatentState):
        model.latent_reset = cfg.trainer.window  # latent states (messages) were trained over windows this long
    log.info(
        f"diagnosing {Path(ckpt['path']).name} on {len(splits.train)} held-in trajectories "
        f"({len(splits.test)} held out)"
    )
    fixer = Fixer(job, plain_dict(cfg.trainer), params.fix_lr_factor, params.jobs) if cfg.fix else None
    try:
        result = run_loop(
            model,
            splits,
            params,
            job.horizons,
            job.seed,
            None if fixer is None else fixer.finetune,
            None if fixer is None else fixer.save,
            log.info,
            None if fixer is None else fixer.finetune_all,
        )
    except DivergenceError as err:  # the report of what was found is still written, then the error is raised
        write_json(
            job.runtime.output_dir / "diagnosis.json", {"task": "diagnose", "init": ckpt["path"], "error": str(err)}
        )
        raise
    return write_diagnosis(job, result, bool(cfg.fix), eval_options(cfg.eval))


def write_diagnosis(job: Job, result: LoopResult, fix: bool, options: EvalOptions | None = None) -> dict[str, Any]:
    """diagnosis.json, diagnosis.md and plots/ of a finished loop, and the summary box."""
    splits, out_dir = job.splits, job.runtime.output_dir
    assert splits is not None
    options = options or EvalOptions()
    freerun = free_run_before_after(job, result, options)
    if freerun is not None and result.verdict == NOTHING_MISSING:
        why = drifts_beyond_null(job, result, freerun, options)
        if why:  # windows at the null level, but the whole record says otherwise: no claim of completeness
            result.verdict = UNEXPLAINED
            result.judgement.notes.append(why)
    out = summarise(job, result, true_effects(job), fix)
    out["freerun"] = freerun
    out["fixed_spec"] = write_fixed_spec(job, result, out_dir) if fix else None
    if job.model is not None and (options is None or options.plots):
        figures = report.feature_plots(result, splits.test, out_dir)
        out["feature_plots"] = [str(p.relative_to(out_dir)) for p in figures]
    report.plots(result, splits.test.t, out_dir)
    write_json(out_dir / "diagnosis.json", out)
    atomic_write(out_dir / "diagnosis.md", lambda f: f.write(report.markdown(out)), mode="w")
    print_summary(f"mpsim diagnose: {out['data']['name']}", report.summary_rows(out, out_dir))
    return out


@dataclass
class _FinetuneJob:
    """One finetune of `mpsim diagnose fix=true`, self-contained so that it can run in another process."""

    rt: Runtime
    splits: Splits
    ckpt: dict[str, Any]
    model_config: dict[str, Any]  # the model's config with the effects the loop added
    solver: ODESolver
    state_dict: dict[str, torch.Tensor]
    latent_reset: int | None
    trainer: dict[str, Any]  # the trainer's config (plain data), its learning rate already scaled
    seed: int
    tag: str  # the run's directory under fix/


class Fixer:
    """What `fix=true` hands the loop: finetunes of the model with the effects it added (one at a time, or the
    control's and the candidates' at once in spawned processes) and the fixed model's checkpoint."""

    def __init__(self, job: Job, trainer: dict[str, Any], lr_factor: float, jobs: int | None) -> None:
        self.job, self.trainer, self.jobs = job, {**trainer, "lr": trainer["lr"] * lr_factor}, jobs
        self.configured = list(job.model_config.get("effects") or [])

    def fixed_config(self, fixed: Model) -> dict[str, Any]:
        """The model config with the effects the loop added (fitted values) after the configured ones."""
        added = [e.config() for e in fixed.effects[len(self.configured) :]]
        return {**self.job.model_config, "effects": self.configured + added}

    def finetune_job(self, fixed: Model, tag: str, progress: bool = True) -> _FinetuneJob:
        job = self.job
        assert job.splits is not None and job.checkpoint is not None
        latent = fixed.latent_reset if isinstance(fixed, LatentState) else None
        trainer = {**self.trainer, "progress": bool(self.trainer.get("progress", True)) and progress}
        return _FinetuneJob(
            job.runtime,
            job.splits,
            job.checkpoint,
            self.fixed_config(fixed),
            job.solver,
            fixed.state_dict(),
            latent,
            trainer,
            job.seed,
            tag,
        )

    def finetune(self, fixed: Model, tag: str) -> tuple[Model, str]:
        run = self.finetune_job(fixed, tag)
        return _collect(run, _run_finetune(run))

    def finetune_all(self, runs: list[tuple[Model, str]]) -> list[tuple[Model, str] | DivergenceError]:
        """The control's and the candidates' finetunes, in up to `diagnose.jobs` processes at once."""
        jobs = [self.finetune_job(m, tag, progress=i == 0) for i, (m, tag) in enumerate(runs)]
        n = min(len(jobs), _workers(self.jobs, self.job.runtime))
        if n <= 1:
            return serial(self.finetune)(runs)
        log.info(f"{len(jobs)} finetunes in {n} processes (diagnose.jobs); the bar shows the control's")
        ctx = multiprocessing.get_context("spawn")  # fork would copy torch's thread pools mid-use
        with ProcessPoolExecutor(max_workers=n, mp_context=ctx, initializer=_worker_init) as pool:
            futures = [pool.submit(_run_finetune, j) for j in jobs]
            outcomes = [f.result() for f in futures]  # an error other than divergence is raised here
        return [o if isinstance(o, DivergenceError) else _collect(j, o) for j, o in zip(jobs, outcomes, strict=True)]

    def save(self, fixed: Model, k: int) -> str:
        job = self.job
        assert job.splits is not None and job.checkpoint is not None
        fixed_cfg = self.fixed_config(fixed)
        path = job.runtime.output_dir / "fix" / f"round{k}" / "fixed.ckpt"
        extra = {"mode": "diagnose-fix", "init": job.checkpoint["path"]}
        base = checkpoint_base(fixed_cfg, fixed, job.splits.train.meta, extra)
        save_checkpoint(path, {**base, "model": {**base["model"], "state_dict": fixed.state_dict()}})
        return str(path)


def _build_fixed(job: _FinetuneJob) -> Model:
    """The model `job` finetunes: the checkpoint's model config with the added effects, its current weights."""
    ckpt = {**job.ckpt, "model": {**job.ckpt["model"], "config": job.model_config}}
    built = build_model_for(job.model_config, job.solver, job.rt, Shape.of(job.splits.train), ckpt)
    built.load_state_dict(job.state_dict)  # fitted coefficients and refit own parameters
    if isinstance(built, LatentState) and job.latent_reset is not None:
        built.latent_reset = job.latent_reset
    return built


def _run_finetune(job: _FinetuneJob) -> tuple[dict[str, torch.Tensor], str] | DivergenceError:
    """Finetune `job`'s model under fix/<tag>/: (its finetuned weights, best checkpoint), or the divergence."""
    splits = job.splits
    built = _build_fixed(job)
    trainer = build(job.trainer, "trainer")
    run_dir = job.rt.output_dir / "fix" / job.tag
    base = checkpoint_base(job.model_config, built, splits.train.meta, {"mode": "finetune", "init": job.ckpt["path"]})
    trainer.fit(built, splits.train, splits.val, splits.test, run_dir=run_dir, seed=job.seed, checkpoint_base=base)
    if trainer.status_ == "diverged":
        return DivergenceError(trainer.divergence_ or "NaN/inf")
    return built.state_dict(), str(run_dir / "checkpoints" / "best.ckpt")


def _collect(job: _FinetuneJob, outcome: tuple[dict[str, torch.Tensor], str] | DivergenceError) -> tuple[Model, str]:
    """The finetuned model in this process (raises the run's DivergenceError)."""
    if isinstance(outcome, DivergenceError):
        raise outcome
    state, path = outcome
    return _build_fixed(replace(job, state_dict=state)), path


def _worker_init() -> None:
    torch.set_num_threads(1)  # one core per finetune: the small batched solves do not gain from threads


def _workers(jobs: int | None, rt: Runtime) -> int:
    """Processes for parallel finetunes: `diagnose.jobs`, or (null) the CPU cores on a CPU, one on a GPU."""
    if jobs is not None:
        return jobs
    return (
        1
        if rt.device.type != "cpu"
        else len(os.sched_getaffinity(0))
        if hasattr(os, "sched_getaffinity")
        else (os.cpu_count() or 1)
    )


#: held-out trajectories a diagnosis needs: a candidate's gain is a mean over them with a standard error taken
#: from them (Student's t, `mpsim.diagnose.stats.critical`); with 1 there is no standard error, with 2 the bar
#: is 14 standard errors (margin 2)
MIN_HELDOUT = 3


def check_heldout(n: int, total: int = 0, split: list[float] | None = None) -> None:
    """Refuse `n` held-out trajectories (of `total` in a file split by `split`; None: simulated, `data.n_test`)
    when too few to judge a candidate on, before any work (the loop would report "unexplained" for an effect it
    could not test)."""
    if n >= MIN_HELDOUT:
        return
    if split is not None:
        share = math.ceil(10 * MIN_HELDOUT / total) / 10 if total else 1.0
        fix = (
            f"hold out more, e.g. data.split=[{1 - share - 0.1:.1f},0.1,{share:.1f}]"
            if total >= 2 * MIN_HELDOUT and share <= 0.5
            else f"record more trajectories (at least {2 * MIN_HELDOUT})"
        )
        where = f"data.split={split} of the file's {total} trajectories holds out {n}"
    else:
        fix, where = f"give data.n_test={MIN_HELDOUT} or more", f"data.n_test={n}"
    raise DataError(
        f"diagnose judges each candidate by its error gain on held-out trajectories, with a standard error taken "
        f"across them, and needs at least {MIN_HELDOUT}; {where}. {fix[0].upper() + fix[1:]}."
    )


def check_heldout_records(n: int) -> None:
    """Refuse a benchmark's test part (`data.test_path`, `data.test_range`) of fewer than `MIN_HELDOUT`
    trajectories: diagnose judges on them and needs a spread."""
    if n < MIN_HELDOUT:
        raise DataError(
            f"diagnose judges each candidate by its error gain on held-out trajectories, with a standard error taken "
            f"across them, and needs at least {MIN_HELDOUT}; the test part (data.test_path / data.test_range) holds "
            f"{n}. Give more test records or a shorter data.segment (the test records are cut into segments of "
            "it), or diagnose with data.split instead."
        )


def free_run_before_after(job: Job, result: LoopResult, options: EvalOptions) -> dict[str, Any] | None:
    """The field's yardstick on the held-out records (measured data; None for simulated data): each whole held-out
    record free-run from its first samples to its end, open loop with its measured input, by the model as given
    and by the model handed back (when the loop returned another): RMSE in the signal's units and fit % per record
    and measured channel, and a plot of the first record's two runs."""
    records = job.splits.records if job.splits is not None else None
    if records is None or not records.observed_index or job.model is None:
        return None
    models = {"before": job.model}
    if result.model is not None and result.model is not job.model and result.after is not None:
        models["after"] = result.model
    runs = {}
    for key, model in models.items():  # the two models
        try:
            runs[key] = free_run(model, records, options.init_samples, substeps=options.freerun_substeps)
        except DivergenceError as err:
            log.warning(f"the free run of the model {key} the fix failed: {err}")
    if not runs:
        return None
    summaries = {key: summary_of(run, records) for key, run in runs.items()}
    first = summaries[next(iter(summaries))]
    rows = []
    for r, rec in enumerate(first["records"]):  # a loop over the few held-out records
        for channel in rec["channels"]:
            row: dict[str, Any] = {"record": rec["record"], "t0": rec.get("t0"), "channel": channel}
            for key, summ in summaries.items():
                scores = summ["records"][r]
                row[f"{key}_rmse"] = math.nan if scores["diverged"] else scores["channels"][channel]["rmse"]
                row[f"{key}_fit"] = math.nan if scores["diverged"] else scores["channels"][channel]["fit"]
            rows.append(row)
    if options.plots:
        lengths = [int(r["length"]) for r in first["records"]]
        channels = records.observed_index
        n, names = lengths[0], [records.state_names[d] for d in channels]
        t0 = float(first["records"][0].get("t0") or 0.0)
        for key, run in runs.items():  # before and after
            plotting.free_run(
                records.t[:n] - records.t[0] + t0,
                records.x[0, :n, 0][:, channels],
                run.pred[0, :n, 0][:, channels],
                names,
                run.init_samples,
                job.runtime.output_dir / "plots" / f"free_run_{key}.png",
                title=f"free run of the held-out record, model {'as given' if key == 'before' else 'with the fix'}",
            )
    return {
        "init_samples": first["init_samples"],
        "init_samples_given": options.init_samples is not None,
        "substeps": options.freerun_substeps,
        "rows": rows,
    }


def write_fixed_spec(job: Job, result: LoopResult, out_dir: Path) -> dict[str, Any] | None:
    """`fixed.yaml` of a fixed `model=equations` model (None for any other): the user's spec with every effect the
    returned model carries written into its equations (`mpsim.diagnose.fixed`), read back as a plain spec and
    checked: its held-out MSE beside the fixed model's (the same windows), and what could not be written."""
    fixed = result.model
    if not isinstance(fixed, EquationsModel) or fixed is job.model or result.after is None or job.splits is None:
        return None
    spec, left_out = written_spec(fixed)
    path = out_dir / "fixed.yaml"
    header = (
        "# The model diagnose fix=true returned, as a spec: the named effects written into the equations, their\n"
        "# coefficients as parameters at the fitted values. Train or evaluate it with\n"
        f"#   mpsim train model=equations model.spec={path.name}\n"
        + "".join(f"# NOT written (carry it as model.effects): {why}\n" for why in left_out)
    )
    text = header + yaml.safe_dump(spec, sort_keys=False, allow_unicode=True)
    atomic_write(path, lambda f: f.write(text), mode="w")
    check: dict[str, Any] = {"path": path.name, "left_out": left_out}
    try:
        rebuilt = EquationsModel(fixed.state_dim, fixed.control_dim, spec=spec, solver=fixed.solver)
        rebuilt = rebuilt.to(dtype=fixed.state_mean.dtype)
        rebuilt.bind_effects(job.splits.test.state_names)
        rebuilt.set_normalisation(fixed.state_mean.detach(), fixed.state_std.detach())
        horizon = result.judgement.horizon
        check["heldout_mse"] = float(window_error(rebuilt, job.splits.test, horizon).mean())
        check["fixed_model_heldout_mse"] = float(window_error(fixed, job.splits.test, horizon).mean())
    except (ConfigError, DivergenceError) as err:  # written, but it does not read back: said, not hidden
        check["read_back_error"] = str(err)
        log.warning(f"fixed.yaml does not read back as a spec: {err}")
    return check


#: *nothing missing* on measured data also needs every held-out record's free-run RMSE within this factor of the
#: same model's free run of its own simulation of that record (with the data's noise): the null free run
FREE_RUN_NULL_FACTOR = 3.0


def drifts_beyond_null(job: Job, result: LoopResult, freerun: dict[str, Any], options: EvalOptions) -> str:
    """Why a *nothing missing* verdict does not hold up over whole records ("" when it does). Held-out windows
    start from the data (their latent part fitted to each window), so an effect slower than a window — a seepage
    from an unmeasured tank — can hide in the latent starts; the free run of a whole record cannot hide it. The
    model that was judged complete free-runs its own simulation of each held-out record (the same input, the
    data's noise: `null_data`), and the free-run RMSE on the data (per channel, RMS over the records) must be
    within `FREE_RUN_NULL_FACTOR` of that."""
    records = job.splits.records if job.splits is not None else None
    model = result.judgement.model or job.model
    if records is None or model is None:
        return ""
    noise = torch.tensor(result.diagnosis.noise_std, dtype=torch.float64)
    try:
        null = null_data(model, records, noise, job.seed + 31)
        run = free_run(model, null, options.init_samples, substeps=options.freerun_substeps)
    except DivergenceError:
        return ""
    null_rows = summary_of(run, null)["records"]
    data_sq: dict[str, list[float]] = {}
    null_sq: dict[str, list[float]] = {}
    for row in freerun["rows"]:  # the few held-out records and channels
        match = [rec for rec in null_rows if rec["record"] == row["record"] and rec["t0"] == row["t0"]]
        level = match[0]["channels"].get(row["channel"], {}).get("rmse", math.nan) if match else math.nan
        data_sq.setdefault(row["channel"], []).append(row["before_rmse"] ** 2)
        null_sq.setdefault(row["channel"], []).append(level**2)
    worst = None
    for channel, values in data_sq.items():  # per channel: RMS over the records (one record's start is a draw)
        on_data = math.sqrt(sum(values) / len(values))
        on_null = math.sqrt(sum(null_sq[channel]) / len(values))
        ratio = on_data / on_null if on_null > 0 else math.inf
        if not ratio <= FREE_RUN_NULL_FACTOR and (worst is None or ratio > worst[0]):
            worst = (ratio, channel, on_data, on_null)
    if worst is None:
        return ""
    ratio, channel, on_data, on_null = worst
    return (
        f"not *nothing missing*: the held-out windows are at the null level, but the free runs of the "
        f"{len(data_sq[channel])} whole held-out records drift to RMSE {on_data:.3g} on {channel} (RMS over the "
        f"records), {ratio:.3g}× the model's free runs of its own simulation of them ({on_null:.3g}, needs ≤ "
        f"{FREE_RUN_NULL_FACTOR:g}×): something slower than a window is missing (the windows' fitted latent starts "
        "absorb it), or the records' starts cannot be estimated. Nothing is claimed"
    )


def summarise(job: Job, result: LoopResult, truths: list[dict[str, Any]], fix: bool) -> dict[str, Any]:
    """diagnosis.json: the verdict with its numbers, what was named and fixed, against the truth where known."""
    splits, ckpt = job.splits, job.checkpoint
    assert splits is not None and ckpt is not None
    j, diag = result.judgement, result.diagnosis
    named = [{**t.as_dict(), "vs_truth": _compare(t.effect, truths)} for t in result.named]
    fixed = []
    if result.model is not None and result.after is not None:
        fixed = [
            {"effect": e.config(), "describe": e.describe(), "vs_truth": _compare(e.config(), truths)}
            for e in result.model.effects
        ]
    verdict = result.verdict
    verdict_note = ""
    if fix and verdict == EFFECTS_NAMED and result.after is None:
        verdict_note = (
            result.rejected[0]["why"] if result.rejected else "no fix was kept"
        ) + "; the model is returned unchanged"
    return {
        "task": "diagnose",
        "init": ckpt["path"],
        "data": {
            "name": splits.train.system_name,
            "source": job.data.path or "simulated",
            "n_heldin": len(splits.train),
            "n_heldout": len(splits.test),
            **data_record(splits),
        },
        "verdict": verdict,
        "verdict_note": verdict_note,
        "exit_code": result.exit_code,
        "effects_named": named,
        "judgement": j.as_dict(),
        "finetuned": [f.as_dict() for f in result.finetuned],
        "screen": diag.as_dict(),
        "before": result.before,
        "after": result.after,
        "rounds": result.rounds,
        "rejected_fixes": result.rejected,
        "fixed_effects": fixed,
        "fixed_checkpoint": result.checkpoint,
        "true_effects": truths,
    }
