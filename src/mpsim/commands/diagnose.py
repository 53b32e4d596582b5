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
from omegaconf import DictConfig, OmegaConf

from mpsim.commands.building import Shape, build, build_model_for, build_system, model_and_data
from mpsim.commands.checkpoints import checkpoint_base, load_init
from mpsim.commands.runtime import Runtime, setup_runtime
from mpsim.console import print_summary
from mpsim.data.dataset import Splits
from mpsim.diagnose import report
from mpsim.diagnose.finetuned import serial
from mpsim.diagnose.heldout import EFFECTS_NAMED
from mpsim.diagnose.loop import LoopResult, holdout_metrics, run_loop
from mpsim.diagnose.params import DiagnoseParams
from mpsim.errors import ConfigError, DataError, DivergenceError
from mpsim.files import atomic_write, write_json
from mpsim.models.base import Model
from mpsim.models.capabilities import LatentState
from mpsim.training.checkpoint import save_checkpoint

log = logging.getLogger(__name__)

__all__ = ["holdout_metrics", "run_diagnose"]


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
            k: abs(found[k] - true[k]) / abs(true[k])
            for k in keys
            if isinstance(true.get(k), int | float) and isinstance(found.get(k), int | float) and true[k]
        }
        return out
    return None


def _params(cfg: DictConfig) -> DiagnoseParams:
    values = OmegaConf.to_container(cfg.diagnose, resolve=True)
    return DiagnoseParams(**values)  # type: ignore[arg-type]


def run_diagnose(cfg: DictConfig, output_dir: str | Path | None = None, overrides: list[str] | None = None) -> dict:
    """Diagnose `init=` on held-in data, judge on held-out data; with `fix=true` also add, finetune, compare."""
    params = _params(cfg)  # settings are checked before anything is read or built
    rt = setup_runtime(cfg, output_dir, overrides)
    if not cfg.init:
        raise ConfigError("mpsim diagnose needs init=<checkpoint> (the trained model to diagnose).")
    ckpt = load_init(cfg, rt)
    assert ckpt is not None  # cfg.init is set
    if not cfg.data.path:  # simulated: its held-out count is known before anything is simulated
        _check_heldout(cfg, int(cfg.data.n_test))
    system = None if cfg.data.path and cfg.data.graph != "system" else build_system(cfg)
    model, model_cfg, splits = model_and_data(cfg, rt, system, ckpt, refit=False, training=bool(cfg.fix))
    _check_heldout(cfg, len(splits.test), len(splits.train) + len(splits.val) + len(splits.test))
    if isinstance(model, LatentState):
        model.latent_reset = cfg.trainer.window  # latent states (messages) were trained over windows this long
    horizons = list(cfg.eval.horizons)
    log.info(
        f"diagnosing {Path(ckpt['path']).name} on {len(splits.train)} held-in trajectories "
        f"({len(splits.test)} held out)"
    )

    def fixed_config(fixed: Model) -> dict[str, Any]:
        """The model config with the effects the loop added (fitted values) after the configured ones."""
        configured = list(model_cfg.get("effects") or [])
        return {**model_cfg, "effects": configured + [e.config() for e in fixed.effects[len(configured) :]]}

    def job(fixed: Model, tag: str, progress: bool = True) -> _FinetuneJob:
        latent = fixed.latent_reset if isinstance(fixed, LatentState) else None
        return _FinetuneJob(
            cfg, rt, splits, ckpt, fixed_config(fixed), fixed.state_dict(), latent, params.fix_lr_factor, tag, progress
        )

    def finetune(fixed: Model, tag: str) -> tuple[Model, str]:
        return _collect(job(fixed, tag), _run_finetune(job(fixed, tag)))

    def finetune_all(runs: list[tuple[Model, str]]) -> list[tuple[Model, str] | DivergenceError]:
        """The control's and the candidates' finetunes, in up to `diagnose.jobs` processes at once."""
        jobs = [job(m, tag, progress=i == 0) for i, (m, tag) in enumerate(runs)]
        n = min(len(jobs), _workers(params.jobs, rt))
        if n <= 1:
            return serial(finetune)(runs)
        log.info(f"{len(jobs)} finetunes in {n} processes (diagnose.jobs); the bar shows the control's")
        ctx = multiprocessing.get_context("spawn")  # fork would copy torch's thread pools mid-use
        with ProcessPoolExecutor(max_workers=n, mp_context=ctx, initializer=_worker_init) as pool:
            futures = [pool.submit(_run_finetune, j) for j in jobs]
            outcomes = [f.result() for f in futures]  # an error other than divergence is raised here
        return [o if isinstance(o, DivergenceError) else _collect(j, o) for j, o in zip(jobs, outcomes, strict=True)]

    def save(fixed: Model, k: int) -> str:
        fixed_cfg = fixed_config(fixed)
        path = rt.output_dir / "fix" / f"round{k}" / "fixed.ckpt"
        base = checkpoint_base(fixed_cfg, fixed, splits.train.meta, {"mode": "diagnose-fix", "init": ckpt["path"]})
        save_checkpoint(path, {**base, "model": {**base["model"], "state_dict": fixed.state_dict()}})
        return str(path)

    truths = _true_effects(cfg)
    error: DivergenceError | None = None
    try:
        result = run_loop(
            model,
            splits,
            params,
            horizons,
            cfg.seed,
            finetune if cfg.fix else None,
            save if cfg.fix else None,
            log.info,
            finetune_all if cfg.fix else None,
        )
    except DivergenceError as err:  # the report of what was found is still written, then the error is raised
        error, result = err, None
    if result is None:
        write_json(rt.output_dir / "diagnosis.json", {"task": "diagnose", "init": ckpt["path"], "error": str(error)})
        raise error  # type: ignore[misc]
    out = _summary(cfg, ckpt, splits, result, truths)
    report.plots(result, splits.test.t, rt.output_dir)
    write_json(rt.output_dir / "diagnosis.json", out)
    atomic_write(rt.output_dir / "diagnosis.md", lambda f: f.write(report.markdown(out)), mode="w")
    print_summary(f"mpsim diagnose: {out['data']['name']}", report.summary_rows(out, rt.output_dir))
    return out


@dataclass
class _FinetuneJob:
    """One finetune of `mpsim diagnose fix=true`, self-contained so that it can run in another process."""

    cfg: DictConfig
    rt: Runtime
    splits: Splits
    ckpt: dict[str, Any]
    model_config: dict[str, Any]  # the model's config with the effects the loop added
    state_dict: dict[str, torch.Tensor]
    latent_reset: int | None
    lr_factor: float
    tag: str  # the run's directory under fix/
    progress: bool


def _build_fixed(job: _FinetuneJob) -> Model:
    """The model `job` finetunes: the checkpoint's model config with the added effects, its current weights."""
    ckpt = {**job.ckpt, "model": {**job.ckpt["model"], "config": job.model_config}}
    built, _ = build_model_for(job.cfg, job.rt, Shape.of(job.splits.train), ckpt)
    built.load_state_dict(job.state_dict)  # fitted coefficients and refit own parameters
    if isinstance(built, LatentState) and job.latent_reset is not None:
        built.latent_reset = job.latent_reset
    return built


def _run_finetune(job: _FinetuneJob) -> tuple[dict[str, torch.Tensor], str] | DivergenceError:
    """Finetune `job`'s model under fix/<tag>/: (its finetuned weights, best checkpoint), or the divergence."""
    cfg, splits = job.cfg, job.splits
    built = _build_fixed(job)
    trainer = build(
        cfg.trainer, "trainer", lr=cfg.trainer.lr * job.lr_factor, progress=cfg.trainer.progress and job.progress
    )
    run_dir = job.rt.output_dir / "fix" / job.tag
    base = checkpoint_base(job.model_config, built, splits.train.meta, {"mode": "finetune", "init": job.ckpt["path"]})
    trainer.fit(built, splits.train, splits.val, splits.test, run_dir=run_dir, seed=cfg.seed, checkpoint_base=base)
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


def _check_heldout(cfg: DictConfig, n: int, total: int = 0) -> None:
    """Refuse `n` held-out trajectories (of `total` in a file) when too few to judge a candidate on, before any
    work (the loop would report "unexplained" for an effect it could not test)."""
    if n >= MIN_HELDOUT:
        return
    if cfg.data.path:
        share = math.ceil(10 * MIN_HELDOUT / total) / 10 if total else 1.0
        fix = (
            f"hold out more, e.g. data.split=[{1 - share - 0.1:.1f},0.1,{share:.1f}]"
            if total >= 2 * MIN_HELDOUT and share <= 0.5
            else f"record more trajectories (at least {2 * MIN_HELDOUT})"
        )
        where = f"data.split={list(cfg.data.split)} of the file's {total} trajectories holds out {n}"
    else:
        fix, where = f"give data.n_test={MIN_HELDOUT} or more", f"data.n_test={n}"
    raise DataError(
        f"diagnose judges each candidate by its error gain on held-out trajectories, with a standard error taken "
        f"across them, and needs at least {MIN_HELDOUT}; {where}. {fix[0].upper() + fix[1:]}."
    )


def _summary(cfg, ckpt, splits, result: LoopResult, truths) -> dict[str, Any]:
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
    if cfg.fix and verdict == EFFECTS_NAMED and result.after is None:
        verdict_note = (
            result.rejected[0]["why"] if result.rejected else "no fix was kept"
        ) + "; the model is returned unchanged"
    return {
        "task": "diagnose",
        "init": ckpt["path"],
        "data": {
            "name": splits.train.system_name,
            "source": cfg.data.path or "simulated",
            "n_heldin": len(splits.train),
            "n_heldout": len(splits.test),
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
