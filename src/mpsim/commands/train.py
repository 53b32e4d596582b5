"""`mpsim train`: build data and model, then train from scratch, finetune from `init=`, or (mode=zeroshot)
evaluate `init=` without training. Writes metrics.csv, summary.json, checkpoints/{best,last}.ckpt, plots/,
and exports the best checkpoint as <paths.ckpt_dir>/<system name>.ckpt."""

from __future__ import annotations

import logging
import math
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from mpsim import plotting
from mpsim.commands.building import build
from mpsim.commands.guards import check_training_memory, noisy_train
from mpsim.commands.prepare import Job, prepare, resolve_mode
from mpsim.commands.resumed import record_stopping
from mpsim.commands.runtime import describe_device, is_multirun, resolve_path
from mpsim.commands.scoring import (
    EvalOptions,
    eval_options,
    evaluate_checkpoint,
    free_run_rows,
    free_run_scores,
    horizon_rows,
    score,
)
from mpsim.config import check_target_node, plain_dict
from mpsim.console import duration, fmt, print_summary
from mpsim.data.account import data_record
from mpsim.errors import ConfigError, OutputError
from mpsim.files import atomic_write, child_path, file_sha256, keep_previous, safe_name, write_json
from mpsim.metrics import epochs_x_min_error
from mpsim.training import distributed
from mpsim.training.checkpoint import capped_meta, checkpoint_base
from mpsim.training.loggers import Logger, LoggerGroup, flatten
from mpsim.training.trainer import Trainer
from mpsim.version import __version__

log = logging.getLogger(__name__)

# summary.json entries that `objective=` may name (a dotted path goes inside a mapping: test.rmse, final.val_error)
OBJECTIVES = (
    "best_val_error",
    "min_test_error",
    "epochs_x_min_error",
    "initial_test_error",
    "final",
    "test",
    "min_test_error_epoch",
    "best_epoch",
    "epochs_run",
    "wall_time",
    "command_time",
)


@dataclass(frozen=True)
class Outputs:
    """What a finished training run writes besides its run directory: the export, the sweep objective, the
    scoring of its best model."""

    export: bool  # copy best.ckpt to <ckpt_dir>/<system name>.ckpt
    ckpt_dir: str
    objective: str
    eval: EvalOptions


def run_train(cfg: DictConfig, output_dir: str | Path | None = None, overrides: list[str] | None = None) -> dict:
    """Run one training job; returns the summary (also written to summary.json), whose ``objective`` entry
    holds the value named by `objective=` (what a Hydra sweeper such as Optuna minimises).

    Under `torchrun` every process runs this; they train one model data-parallel (`mpsim.training.distributed`),
    and rank 0 alone evaluates the result and writes files."""
    started = time.perf_counter()
    _check_objective(cfg.get("objective"))
    zero_shot = resolve_mode(cfg.mode.name, cfg.init) == "zeroshot"
    job = prepare(cfg, "train", output_dir, overrides, training=not zero_shot, distributed_run=True)
    outputs = Outputs(
        bool(cfg.export),
        str(cfg.paths.ckpt_dir),
        str(cfg.objective),
        eval_options(cfg.eval),
    )
    done = False
    try:
        if zero_shot:
            summary = evaluate_checkpoint(job, outputs.eval, "train", started) if job.dist.is_main else _rank_only(job)
        else:
            trainer = build(plain_dict(cfg.trainer), "trainer")
            loggers = build_loggers(plain_dict(cfg.logger) if cfg.get("logger") and job.dist.is_main else {})
            if job.resumed is not None and job.dist.is_main:
                record_stopping(
                    job.runtime.output_dir, {k: cfg.trainer[k] for k in ("max_epochs", "early_stop_patience")}
                )
            loggers.start(job.runtime.output_dir, flatten(plain_dict(cfg)), _history(job))
            summary = train(job, trainer, loggers, outputs, started)
        done = True
        return summary
    finally:  # after a success the ranks leave together (rank 1 waits for rank 0's evaluation); not after an error
        distributed.teardown(job.dist, together=done)


def _rank_only(job: Job) -> dict[str, Any]:
    return {"task": "train", "rank": job.dist.rank}


def _history(job: Job) -> list[dict[str, Any]]:
    return [] if job.resumed is None else job.resumed["trainer"]["history"]


def train(job: Job, trainer: Trainer, loggers: LoggerGroup, outputs: Outputs, started: float) -> dict:
    """Train `job`'s model with `trainer` (resuming its run where `job.resumed` says), then score the best model,
    write the summary and export the checkpoint. Rank 0 alone scores and writes."""
    model, splits, rt = job.model, job.splits, job.runtime
    assert model is not None and splits is not None  # prepared with data
    if job.dist.is_main and job.resumed is None and job.data.from_file:  # `resume=` accepts the file moved along
        data_file = resolve_path(str(job.data.path), rt.start_dir)
        if data_file.is_file():  # one file (a pattern's files are read afresh)
            write_json(rt.output_dir / "data.json", {"path": str(data_file), "sha256": file_sha256(data_file)})
    if job.data.noise_std > 0:
        std = model.state_std.detach().cpu().double()
        splits = noisy_train(splits, std, job.data.noise_std, job.data.seed, rt.dtype)
    train_split = splits.train
    if job.resumed is None:
        log.info(
            f"{job.mode}: {model.describe()['model']} ({model.describe()['n_params']:,} params) on "
            f"{train_split.system_name}: {len(train_split)}/{len(splits.val)}/{len(splits.test)} trajectories, "
            f"N={train_split.n_nodes}, {train_split.n_times - 1} steps of {fmt(train_split.meta.get('dt'))}"
        )
    base = checkpoint_base(
        job.model_config,
        model,
        train_split.meta,
        {"mode": job.mode, "init": _init_path(job), "mpsim_version": __version__},
    )
    check_training_memory(rt, model, job.model_config, train_split, trainer.batch_size, trainer.window)
    trainer.fit(
        model,
        train_split,
        splits.val,
        splits.test,
        run_dir=rt.output_dir,
        seed=job.seed,
        checkpoint_base=base,
        resume_state=None if job.resumed is None else job.resumed["trainer"],
        on_epoch=loggers.log_epoch,
        dist=job.dist,
    )
    if not job.dist.is_main:  # rank 0 evaluates the trained model and writes the run's files
        return {**_rank_only(job), "status": trainer.status_, "best_val_error": trainer.best_val_}
    return finish(job, trainer, loggers, outputs, started)


def _init_path(job: Job) -> str | None:
    if job.resumed is not None:
        return job.resumed.get("init")
    return None if job.checkpoint is None else job.checkpoint["path"]


def finish(job: Job, trainer: Trainer, loggers: LoggerGroup, outputs: Outputs, started: float) -> dict:
    """After training: learning curves, the best model scored on the test split, summary.json, the export."""
    model, splits, rt = job.model, job.splits, job.runtime
    assert model is not None and splits is not None
    train_split = splits.train
    history = trainer.history_
    plotting.learning_curves(
        history, rt.output_dir / "plots" / "learning_curves.png", title=f"{train_split.system_name}: {job.mode}"
    )
    title = f"{train_split.system_name}: {job.mode}, best epoch {trainer.best_epoch_}"
    metrics = score(job, model, splits.test, outputs.eval, title)
    best_path = rt.output_dir / "checkpoints" / "best.ckpt"
    exported, previous, export_error = None, None, None
    try:  # a failed export must not lose the run: the summary is written first, then the error is reported
        # the best epoch may be 0 (e.g. a white-box model already at its optimum); a run that diverged before
        # improving on its start exports nothing
        usable = trainer.best_epoch_ >= 1 or trainer.status_ != "diverged"
        if usable and outputs.export:
            exported, previous = export(
                best_path, resolve_path(outputs.ckpt_dir, rt.start_dir), train_split.system_name
            )
    except OutputError as err:
        export_error = err
    summary = summarise(job, trainer, metrics, started)
    summary["freerun"] = free_run_scores(job, model, splits.records, outputs.eval, title)
    summary.update(
        {
            "checkpoint": str(best_path),
            "exported": None if exported is None else str(exported),
            "export_replaced": None if previous is None else str(previous),
            "export_error": None if export_error is None else str(export_error),
        }
    )
    summary["objective"] = {"name": outputs.objective, "value": objective_value(summary, outputs.objective)}
    write_json(rt.output_dir / "summary.json", summary)
    loggers.finish(summary)
    _print(summary, train_split, model.report_lines())
    if export_error is not None:
        raise OutputError(
            f"{export_error} The run itself is complete: its model is {best_path} and its summary "
            f"{rt.output_dir / 'summary.json'}."
        )
    return summary


def summarise(job: Job, trainer: Trainer, metrics: dict[str, Any], started: float) -> dict[str, Any]:
    """summary.json of a finished training run (without its export entries and objective)."""
    model, splits, rt, data = job.model, job.splits, job.runtime, job.data
    assert model is not None and splits is not None
    train_split, history = splits.train, trainer.history_
    trained = [r for r in history if r["epoch"] >= 1]
    table2 = epochs_x_min_error([r["epoch"] for r in trained], [r["test_error"] for r in trained])
    params = {k: v for k, v in train_split.meta.get("params", {}).items() if k != "H"}
    return {
        "task": "train",
        "mode": job.mode,
        "status": trainer.status_,
        "divergence": trainer.divergence_,
        "init": _init_path(job),
        "system": {
            "name": train_split.system_name,
            "n_nodes": train_split.n_nodes,
            "state_names": train_split.state_names,
            "params": capped_meta(params, "summary.json"),
        },
        "model": {**model.describe(), "config": job.model_config, **model.report()},
        "data": {
            **splits.sizes(),
            "n_times": train_split.n_times,
            "dt": train_split.meta.get("dt"),
            "source": data.path or "simulated",
            "seed": data.seed,
            "noise_std": data.noise_std,
            **data_record(splits),
        },
        "seed": job.seed,
        "epochs_run": history[-1]["epoch"],
        "best_epoch": trainer.best_epoch_,
        "best_val_error": trainer.best_val_,
        **table2,
        "initial_test_error": history[0]["test_error"],
        "final": {"val_error": history[-1]["val_error"], "test_error": history[-1]["test_error"]},
        "test": metrics,
        "wall_time": history[-1]["wall_time"],
        "command_time": time.perf_counter() - started,
        "run_dir": str(rt.output_dir),
        "distributed": {"world_size": job.dist.world_size, "backend": job.dist.backend},
        "device": describe_device(rt.device),
    }


def build_loggers(nodes: dict[str, Any]) -> LoggerGroup:
    """The loggers of the `logger` group (one `_target_` node per key; null or empty: none)."""
    loggers = []
    for name, node in nodes.items():
        if node is None:
            continue
        check_target_node(node, f"logger.{name}")
        logger = build(node, f"logger.{name}")
        if not isinstance(logger, Logger):
            raise ConfigError(f"logger.{name}._target_={node.get('_target_')} is not an mpsim.training.loggers.Logger.")
        loggers.append(logger)
    return LoggerGroup(loggers)


def _check_objective(name: str | None) -> None:
    if not name or name.split(".")[0] not in OBJECTIVES:
        raise ConfigError(
            f"objective={name!r} is not a result of mpsim train; choose one of {', '.join(OBJECTIVES)} "
            "(a dotted name reads inside final/test, e.g. objective=test.rmse)."
        )


def objective_value(summary: dict[str, Any], name: str) -> float:
    """The summary entry `name` (dotted: inside mappings) as a float; NaN when it is missing a value.

    Raises:
        ConfigError: `name` names no number in the summary.
    """
    value: Any = summary
    for part in name.split("."):
        if not isinstance(value, dict) or part not in value:
            numbers = sorted(
                k for k, v in flatten(summary).items() if isinstance(v, int | float) and not isinstance(v, bool)
            )
            raise ConfigError(f"objective={name!r} is not in this run's summary; numbers it has: {', '.join(numbers)}.")
        value = value[part]
    if value is None:
        return math.nan
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(f"objective={name!r} is {value!r}, not a number.")
    return float(value)


def export(best: Path, ckpt_dir: Path, name: str) -> tuple[Path | None, Path | None]:
    """Copy best.ckpt to <ckpt_dir>/<name>.ckpt atomically (so `init=<name>.ckpt` finds it).

    No run silently replaces another run's model: a sweep job exports nothing (its model stays in its own run
    directory), and a single run that replaces an existing export first keeps it as
    ``<name>.<its modification time>.ckpt`` beside it. `name` comes from the data (e.g. a file's ``meta.system``)
    and is reduced to ``[A-Za-z0-9_.-]``, so the export stays inside `ckpt_dir`.

    Returns:
        (the exported file, where the model it replaced was kept), each None when there is none.
    """
    if not best.is_file() or is_multirun():
        return None, None
    dest = child_path(ckpt_dir, f"{safe_name(name)}.ckpt")
    previous = keep_previous(dest) if dest.is_file() else None
    with open(best, "rb") as src:
        atomic_write(dest, lambda f: shutil.copyfileobj(src, f))
    if previous is not None:
        log.warning(f"replaced {dest}; the model it held is kept as {previous}")
    return dest, previous


def _print(s: dict[str, Any], train, model_lines: list[tuple[str, str]]) -> None:
    title = f"mpsim train: {s['system']['name']} ({s['mode']})"
    rows = [
        (
            "model",
            f"{s['model']['model']} ({s['model']['n_params']:,} params)" + (f", from {s['init']}" if s["init"] else ""),
        ),
        (
            "data",
            f"{s['data']['train']}/{s['data']['val']}/{s['data']['test']} train/val/test trajectories, "
            f"N={train.n_nodes}, {train.n_times - 1} steps of {fmt(train.meta.get('dt'))}",
        ),
        (
            "epochs",
            f"{s['epochs_run']} ({s['status'].replace('_', ' ')}), wall time {duration(s['wall_time'])}"
            + (f" on {s['device']}" if s.get("device") else ""),
        ),
        (
            "min test error",
            f"{fmt(s['min_test_error'])} at epoch {s['min_test_error_epoch']} "
            f"(untrained/initial: {fmt(s['initial_test_error'])})",
        ),
        ("epochs_x_min_error", fmt(s["epochs_x_min_error"])),
        ("final val/test error", f"{fmt(s['final']['val_error'])} / {fmt(s['final']['test_error'])}"),
        ("best model test RMSE", f"{fmt(s['test']['rmse'])} normalised, {fmt(s['test']['rmse_raw'])} raw"),
        *horizon_rows(s["test"]),
        *model_lines,
    ]
    if "energy_error" in s["test"]:
        rows.append(
            (
                "energy error",
                f"{fmt(s['test']['energy_error'])} (data's own drift {fmt(s['test']['data_energy_drift'], 2)})",
            )
        )
    if s["divergence"]:
        rows.append(("diverged", s["divergence"]))
    rows += free_run_rows(s.get("freerun"))
    rows.append(("run dir", s["run_dir"]))
    if s["exported"]:
        rows.append(("checkpoint", f"{s['exported']}  (use init={Path(s['exported']).name})"))
        if s.get("export_replaced"):
            rows.append(("", f"replaced an earlier export, kept as {s['export_replaced']}"))
    elif s["best_epoch"] >= 1:
        why = "a sweep job: its model stays in its run directory" if is_multirun() else "not exported"
        rows.append(("checkpoint", f"{s['checkpoint']}  ({why}; use init={s['checkpoint']})"))
    print_summary(title, rows)
