"""`mpsim train`: build data and model, then train from scratch, finetune from `init=`, or (mode=zeroshot)
evaluate `init=` without training. Writes metrics.csv, summary.json, checkpoints/{best,last}.ckpt, plots/,
and exports the best checkpoint as <paths.ckpt_dir>/<system name>.ckpt."""

from __future__ import annotations

import logging
import math
import shutil
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import yaml
from omegaconf import DictConfig, OmegaConf

from mpsim import plotting
from mpsim.commands.building import build, build_system, model_and_data
from mpsim.commands.checkpoints import capped_meta, checkpoint_base, load_init
from mpsim.commands.evaluation import evaluate_checkpoint, evaluate_model, horizon_rows
from mpsim.commands.runtime import Runtime, describe_device, is_multirun, resolve_path, setup_runtime
from mpsim.commands.splits import check_training_memory, noisy_train
from mpsim.config import check_target_node, plain_dict, read_overrides_file
from mpsim.console import duration, fmt, print_summary
from mpsim.errors import CheckpointError, ConfigError, DataError, OutputError
from mpsim.files import atomic_write, child_path, file_sha256, keep_previous, safe_name, write_json
from mpsim.metrics import epochs_x_min_error
from mpsim.safeload import RECORD_BYTES, load_yaml
from mpsim.training import distributed
from mpsim.training.checkpoint import load_checkpoint
from mpsim.training.distributed import DistContext
from mpsim.training.loggers import Logger, LoggerGroup, flatten
from mpsim.training.trainer import check_resume
from mpsim.version import __version__

log = logging.getLogger(__name__)

MODES = ("scratch", "finetune", "zeroshot")
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


def resolve_mode(name: str, init: str | None) -> str:
    """scratch (default) becomes finetune when `init=` is given; finetune and zeroshot need `init=`."""
    if name not in MODES:
        raise ConfigError(f"mode={name!r} is unknown; choose one of {', '.join(MODES)}.")
    if name == "scratch":
        return "finetune" if init else "scratch"
    if not init:
        raise ConfigError(f"mode={name} needs init=<checkpoint> (a path, or a name in paths.ckpt_dir).")
    return name


def run_train(cfg: DictConfig, output_dir: str | Path | None = None, overrides: list[str] | None = None) -> dict:
    """Run one training job; returns the summary (also written to summary.json), whose ``objective`` entry
    holds the value named by `objective=` (what a Hydra sweeper such as Optuna minimises).

    Under `torchrun` every process runs this; they train one model data-parallel (`mpsim.training.distributed`),
    and rank 0 alone evaluates the result and writes files."""
    rt = setup_runtime(cfg, output_dir, overrides)
    _check_objective(cfg.get("objective"))
    ctx = distributed.setup(rt.device)
    done = False
    try:
        summary = _run(cfg, replace(rt, device=ctx.device), ctx)
        done = True
        return summary
    finally:  # after a success the ranks leave together (rank 1 waits for rank 0's evaluation); not after an error
        distributed.teardown(ctx, together=done)


def _run(cfg: DictConfig, rt: Runtime, ctx: DistContext) -> dict:
    mode = resolve_mode(cfg.mode.name, cfg.init)
    if mode == "zeroshot":
        return evaluate_checkpoint(cfg, rt, task="train") if ctx.is_main else {"task": "train", "rank": ctx.rank}
    t0 = time.perf_counter()
    last = _resume_checkpoint(cfg, rt)
    ckpt = load_init(cfg, rt) if last is None else None
    system = None if cfg.data.path and cfg.data.graph != "system" else build_system(cfg)
    if not ctx.is_main:  # rank 0 simulates (and caches) the data first; the other ranks then read the cache
        ctx.barrier()
    if last is None:
        model, model_cfg, splits = model_and_data(
            cfg, rt, system, ckpt, bool(cfg.mode.refit_normalisation), training=True
        )
    else:  # the interrupted run's own model (config, weights, normalisation)
        model, model_cfg, splits = model_and_data(cfg, rt, system, last, refit=False, training=True)
    if ctx.is_main:
        ctx.barrier()
        if last is None and cfg.data.path:  # lets `resume=` accept the same file moved along with the run
            data_file = resolve_path(cfg.data.path, rt.start_dir)
            write_json(rt.output_dir / "data.json", {"path": str(data_file), "sha256": file_sha256(data_file)})
    init_path = last.get("init") if last is not None else (None if ckpt is None else ckpt["path"])
    if cfg.data.noise_std > 0:
        std = model.state_std.detach().cpu().double()
        splits = noisy_train(splits, std, cfg.data.noise_std, cfg.data.seed, rt.dtype)
    train, val, test = splits.train, splits.val, splits.test
    if last is None:
        log.info(
            f"{mode}: {model.describe()['model']} ({model.describe()['n_params']:,} params) on "
            f"{train.system_name}: {len(train)}/{len(val)}/{len(test)} trajectories, N={train.n_nodes}, "
            f"{train.n_times - 1} steps of {fmt(train.meta.get('dt'))}"
        )
    base = checkpoint_base(
        model_cfg,
        model,
        train.meta,
        {"mode": mode, "init": init_path, "mpsim_version": __version__},
    )
    check_training_memory(cfg, rt, model, model_cfg, train)
    trainer = build(cfg.trainer, "trainer")
    if last is not None and ctx.is_main:
        _record_stopping(cfg, rt.output_dir)
    loggers = build_loggers(cfg) if ctx.is_main else LoggerGroup()
    loggers.start(
        rt.output_dir,
        flatten(plain_dict(cfg)),
        [] if last is None else last["trainer"]["history"],
    )
    trainer.fit(
        model,
        train,
        val,
        test,
        run_dir=rt.output_dir,
        seed=cfg.seed,
        checkpoint_base=base,
        resume_state=None if last is None else last["trainer"],
        on_epoch=loggers.log_epoch,
        dist=ctx,
    )
    if not ctx.is_main:  # rank 0 evaluates the trained model and writes the run's files
        return {"task": "train", "rank": ctx.rank, "status": trainer.status_, "best_val_error": trainer.best_val_}
    history = trainer.history_
    plotting.learning_curves(
        history, rt.output_dir / "plots" / "learning_curves.png", title=f"{train.system_name}: {mode}"
    )
    metrics = evaluate_model(
        model,
        test,
        rt.output_dir,
        list(cfg.eval.horizons),
        None if cfg.data.path else system,
        cfg.eval.n_plot,
        cfg.eval.plots,
        title=f"{train.system_name}: {mode}, best epoch {trainer.best_epoch_}",
        save_predictions=cfg.eval.save_predictions,
    )
    trained = [r for r in history if r["epoch"] >= 1]
    table2 = epochs_x_min_error([r["epoch"] for r in trained], [r["test_error"] for r in trained])
    best_path = rt.output_dir / "checkpoints" / "best.ckpt"
    exported, previous, export_error = None, None, None
    try:  # a failed export must not lose the run: the summary is written first, then the error is reported
        # the best epoch may be 0 (e.g. a white-box model already at its optimum); a run that diverged before
        # improving on its start exports nothing
        usable = trainer.best_epoch_ >= 1 or trainer.status_ != "diverged"
        exported, previous = _export(best_path, cfg, rt, train.system_name) if usable else (None, None)
    except OutputError as err:
        export_error = err
    summary: dict[str, Any] = {
        "task": "train",
        "mode": mode,
        "status": trainer.status_,
        "divergence": trainer.divergence_,
        "init": init_path,
        "system": {
            "name": train.system_name,
            "n_nodes": train.n_nodes,
            "state_names": train.state_names,
            "params": capped_meta(
                {k: v for k, v in train.meta.get("params", {}).items() if k != "H"}, "summary.json's system.params"
            ),
        },
        "model": {**model.describe(), "config": model_cfg, **model.report()},
        "data": {
            **splits.sizes(),
            "n_times": train.n_times,
            "dt": train.meta.get("dt"),
            "source": cfg.data.path or "simulated",
            "seed": cfg.data.seed,
            "noise_std": cfg.data.noise_std,
        },
        "seed": cfg.seed,
        "epochs_run": history[-1]["epoch"],
        "best_epoch": trainer.best_epoch_,
        "best_val_error": trainer.best_val_,
        **table2,
        "initial_test_error": history[0]["test_error"],
        "final": {"val_error": history[-1]["val_error"], "test_error": history[-1]["test_error"]},
        "test": metrics,
        "wall_time": history[-1]["wall_time"],
        "command_time": time.perf_counter() - t0,
        "run_dir": str(rt.output_dir),
        "checkpoint": str(best_path),
        "exported": None if exported is None else str(exported),
        "export_replaced": None if previous is None else str(previous),
        "export_error": None if export_error is None else str(export_error),
        "distributed": {"world_size": ctx.world_size, "backend": ctx.backend},
        "device": describe_device(rt.device),
    }
    summary["objective"] = {"name": cfg.objective, "value": objective_value(summary, cfg.objective)}
    write_json(rt.output_dir / "summary.json", summary)
    loggers.finish(summary)
    _print(summary, train, model.report_lines())
    if export_error is not None:
        raise OutputError(
            f"{export_error} The run itself is complete: its model is {best_path} and its summary "
            f"{rt.output_dir / 'summary.json'}."
        )
    return summary


def build_loggers(cfg: DictConfig) -> LoggerGroup:
    """The loggers of the `logger` group (one `_target_` node per key; null or empty: none)."""
    loggers = []
    for name, node in (cfg.get("logger") or {}).items():
        if node is None:
            continue
        check_target_node(OmegaConf.to_container(node, resolve=True), f"logger.{name}")
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


def _resume_checkpoint(cfg: DictConfig, rt: Runtime) -> dict | None:
    """`<run dir>/checkpoints/last.ckpt` when `resume` is set (the CLI points the run directory at the run
    being resumed)."""
    if not cfg.resume:
        return None
    last = rt.output_dir / "checkpoints" / "last.ckpt"
    if not last.is_file():
        raise CheckpointError(
            f"resume: no {last}. Resume reruns the same command in the directory of the run it continues; "
            "pass resume=<run dir> to name it, or drop resume=true to start afresh."
        )
    state = load_checkpoint(last)
    if "trainer" not in state:
        raise CheckpointError(f"resume: {last} holds no trainer state.")
    _check_trainer_state(state["trainer"], last)
    check_resume(state["trainer"], int(cfg.trainer.max_epochs), int(cfg.trainer.early_stop_patience))
    return state


def _record_stopping(cfg: DictConfig, run_dir: Path) -> None:
    """Write a resume's new `trainer.max_epochs` / `trainer.early_stop_patience` into the run's `.hydra/` record
    (overrides.yaml and config.yaml, atomically), so a report of the run shows the budget it trained under. The
    rest of the record stays as the run wrote it."""
    record = run_dir / ".hydra"
    try:
        config = load_yaml(record / "config.yaml", RECORD_BYTES, str(record / "config.yaml"), "Restore it")
        overrides = read_overrides_file(run_dir)
    except (OSError, UnicodeDecodeError, yaml.YAMLError, DataError):
        return  # no record to keep up to date (the CLI refused a damaged one and warned of a missing one)
    if not isinstance(config, dict) or not isinstance(config.get("trainer"), dict) or overrides is None:
        return
    changed = {
        key: int(cfg.trainer[key])
        for key in ("max_epochs", "early_stop_patience")
        if config["trainer"].get(key) != int(cfg.trainer[key])
    }
    if not changed:
        return
    for key, value in changed.items():
        config["trainer"][key] = value
        kept = [o for o in overrides if str(o).split("=", 1)[0].lstrip("+~") != f"trainer.{key}"]
        overrides = [*kept, f"trainer.{key}={value}"]
    text = yaml.safe_dump(overrides, sort_keys=False)
    atomic_write(record / "overrides.yaml", lambda f: f.write(text), mode="w")
    config_text = yaml.safe_dump(config, sort_keys=False)
    atomic_write(record / "config.yaml", lambda f: f.write(config_text), mode="w")
    log.info(f"recorded {', '.join(f'trainer.{k}={v}' for k, v in changed.items())} in {record}")


#: what a resume reads from a last.ckpt's trainer state, and the type each must have
_TRAINER_STATE: dict[str, type | tuple[type, ...]] = {
    "epoch": int,
    "best_epoch": int,
    "since_best": int,
    "max_epochs": int,
    "best_val": (int, float),
    "model_state": dict,
    "best_state": dict,
    "optimizer": dict,
    "scheduler": dict,
    "history": list,
}


def _check_trainer_state(trainer: dict, path: Path) -> None:
    """The counters and mappings a resume reads: present (`max_epochs` only in newer files), of their types, the
    counters >= 0 (one message naming the first that is wrong)."""
    import torch

    for key, kind in _TRAINER_STATE.items():
        if key not in trainer:
            if key == "max_epochs":
                continue
            raise CheckpointError(f"resume: {path} lacks 'trainer.{key}'; the file is damaged. Start the run afresh.")
        value = trainer[key]
        if (
            isinstance(value, bool)
            or not isinstance(value, kind)
            or (kind is int and isinstance(value, int) and value < 0)
        ):
            raise CheckpointError(
                f"resume: {path}: 'trainer.{key}' is {value!r:.60}, not what a trainer writes "
                f"({'a count >= 0' if kind is int else 'a ' + getattr(kind, '__name__', 'number')}); the file is "
                "damaged. Start the run afresh."
            )
    if not isinstance(trainer.get("shuffle_rng"), torch.Tensor):
        raise CheckpointError(
            f"resume: {path} lacks the tensor 'trainer.shuffle_rng'; the file is damaged. Start the run afresh."
        )


def _export(best: Path, cfg: DictConfig, rt: Runtime, name: str) -> tuple[Path | None, Path | None]:
    """Copy best.ckpt to <paths.ckpt_dir>/<name>.ckpt atomically (so `init=<name>.ckpt` finds it).

    No run silently replaces another run's model: a sweep job exports nothing (its model stays in its own run
    directory), and a single run that replaces an existing export first keeps it as
    ``<name>.<its modification time>.ckpt`` beside it. `name` comes from the data (e.g. a file's ``meta.system``)
    and is reduced to ``[A-Za-z0-9_.-]``, so the export stays inside `paths.ckpt_dir`.

    Returns:
        (the exported file, where the model it replaced was kept), each None when there is none.
    """
    if not cfg.export or not best.is_file() or is_multirun():
        return None, None
    dest = child_path(resolve_path(cfg.paths.ckpt_dir, rt.start_dir), f"{safe_name(name)}.ckpt")
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
    rows.append(("run dir", s["run_dir"]))
    if s["exported"]:
        rows.append(("checkpoint", f"{s['exported']}  (use init={Path(s['exported']).name})"))
        if s.get("export_replaced"):
            rows.append(("", f"replaced an earlier export, kept as {s['export_replaced']}"))
    elif s["best_epoch"] >= 1:
        why = "a sweep job: its model stays in its run directory" if is_multirun() else "not exported"
        rows.append(("checkpoint", f"{s['checkpoint']}  ({why}; use init={s['checkpoint']})"))
    print_summary(title, rows)
