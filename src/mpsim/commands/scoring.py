"""Scoring a model on a test split: metrics, plots, and the summary of a checkpoint scored without training.
Shared by `mpsim eval` and `mpsim train` (its final test, and `mode=zeroshot`)."""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import torch

from mpsim import plotting
from mpsim.commands.prepare import Job
from mpsim.console import fmt, print_summary
from mpsim.data.account import data_record
from mpsim.data.io import save_npz
from mpsim.data.trajectories import Trajectories
from mpsim.files import write_json
from mpsim.metrics import relative_energy_error, rollout_metrics
from mpsim.models.base import Model
from mpsim.models.freerun import free_run, summary_of
from mpsim.models.rollout import rollout
from mpsim.systems.base import System


def evaluate_model(
    model: Model,
    test: Trajectories,
    output_dir: Path,
    horizons: list[int],
    system: System | None = None,
    n_plot: int = 2,
    plots: bool = True,
    title: str = "",
    save_predictions: bool = False,
) -> dict[str, Any]:
    """Roll `model` out on `test`, compute the common metrics and draw the trajectory/error plots.

    Args:
        system: the generating system, for the energy error (None for file data or energy-free systems).
        save_predictions: also write `test.npz` (the test split) and `test_model.npz` (the model's rollout of
            it from each first state, raw units) to `output_dir`, in `mpsim simulate`'s format.
    """
    pred, aux = rollout(model, test, aux=True)
    if save_predictions:
        save_npz(test, output_dir / "test.npz")
        save_npz(
            replace(test, x=pred.double(), meta={**test.meta, "model": "rollout from each first state"}),
            output_dir / "test_model.npz",
        )
    true = test.x.to(pred.dtype)
    std = model.state_std.detach().cpu().to(pred.dtype)
    metrics = rollout_metrics(
        pred, true, std, test.t, horizons, test.meta.get("periods"), model.context_steps, test.observed_index
    )
    metrics.update(test.measured_states())  # which states were measured, how the others were estimated
    features = test.node_features  # [N, F] or [B, N, F]
    probe = None if features is None else (features[:1] if features.dim() == 3 else features)
    if system is not None and system.energy(test.x[:1, :1], probe) is not None:

        def energy(x: torch.Tensor) -> torch.Tensor:  # x: [B, T, N, D] states
            e = system.energy(x, features)
            assert e is not None  # the probe above found that the system has one
            return e

        metrics.update(relative_energy_error(energy, pred, true))
    if plots:
        plot_dir = output_dir / "plots"
        plotting.trajectories(
            test.t,
            true,
            pred,
            plot_dir / "trajectories.png",
            test.state_names,
            messages=aux.get("messages"),
            n_traj=n_plot,
            title=title,
        )
        plotting.error_growth(test.t, metrics["per_step_rmse"], plot_dir / "error_growth.png", title=title)
    return metrics


def horizon_rows(metrics: dict[str, Any]) -> list[tuple[str, str]]:
    hz = metrics.get("horizons", {})
    if not hz:
        return []
    cells = ", ".join(f"{k} steps (t={fmt(v['t'], 3)}): {fmt(v['rmse'])}" for k, v in hz.items())
    raw = ", ".join(f"{k} steps: {fmt(v['rmse_raw'])}" for k, v in hz.items())
    return [("test RMSE at", f"{cells} (normalised)"), ("", f"{raw} (raw units)")]


@dataclass(frozen=True)
class EvalOptions:
    """How a model is scored on the test split (the `eval.*` keys but `horizons`, which `Job` holds fitted to the
    record)."""

    n_plot: int = 2
    plots: bool = True
    save_predictions: bool = False
    init_samples: int | None = None  # samples that start a free run (None: what the records' latent states need)
    freerun_substeps: int | None = 4  # RK4 steps per sample of a free run (None: the model's own solver)


def eval_options(node: Any) -> EvalOptions:
    """`eval.*` (but `horizons`) as plain values."""
    return EvalOptions(
        int(node.n_plot),
        bool(node.plots),
        bool(node.save_predictions),
        None if node.get("init_samples") is None else int(node.init_samples),
        None if node.get("freerun_substeps") is None else int(node.freerun_substeps),
    )


def free_run_scores(
    job: Job, model: Model, records: Trajectories | None, options: EvalOptions, title: str
) -> dict[str, Any] | None:
    """The free run of every whole test record (measured recordings; None for simulated data): scores per record
    and channel, and a plot of each of the first `n_plot` records."""
    if records is None or not records.observed_index:
        return None
    run = free_run(model, records, options.init_samples, substeps=options.freerun_substeps)
    out = summary_of(run, records)
    out["init_samples_given"] = options.init_samples is not None
    out["substeps"] = options.freerun_substeps
    if options.plots:
        lengths = [r["length"] for r in out["records"]]
        channels = records.observed_index
        names = [records.state_names[d] for d in channels]
        for r in range(min(options.n_plot, len(records))):  # a loop over the few plotted records
            n = int(lengths[r])
            name = Path(str(out["records"][r]["record"])).stem
            t0 = float(out["records"][r].get("t0") or 0.0)
            plotting.free_run(
                records.t[:n] - records.t[0] + t0,
                records.x[r, :n, 0][:, channels],
                run.pred[r, :n, 0][:, channels],
                names,
                run.init_samples,
                job.runtime.output_dir / "plots" / f"free_run_{r}_{name}.png",
                title=f"{title}: {name}",
            )
    return out


def free_run_rows(freerun: dict[str, Any] | None) -> list[tuple[str, str]]:
    """The summary box's lines of a free run: one per record and channel, and how it started."""
    if not freerun:
        return []
    given = "eval.init_samples" if freerun.get("init_samples_given") else "what the latent states need"
    rows = [
        (
            "free run",
            f"each test record from its first {freerun['init_samples']} samples ({given}) to its end, open loop",
        )
    ]
    for rec in freerun["records"]:
        name = Path(str(rec["record"])).name
        if rec["diverged"]:
            rows.append(("", f"{name}: diverged"))
            continue
        for channel, v in rec["channels"].items():
            rows.append(
                (
                    "",
                    f"{name} {channel}: RMSE {fmt(v['rmse'])}, NRMSE {fmt(v['nrmse'])}, fit {v['fit']:.1f} % "
                    f"({v['samples']} samples)",
                )
            )
    return rows


def score(job: Job, model: Model, test: Trajectories, options: EvalOptions, title: str) -> dict[str, Any]:
    """`evaluate_model` with the job's horizons and run directory; the energy error for simulated data."""
    return evaluate_model(
        model,
        test,
        job.runtime.output_dir,
        job.horizons,
        None if job.data.from_file else job.system,
        options.n_plot,
        options.plots,
        title=title,
        save_predictions=options.save_predictions,
    )


def evaluate_checkpoint(job: Job, options: EvalOptions, task: str, started: float) -> dict:
    """Score `job`'s checkpoint on its test split without training: `mpsim eval` and `mpsim train mode=zeroshot`."""
    ckpt, model, splits = job.checkpoint, job.model, job.splits
    assert ckpt is not None and model is not None and splits is not None  # prepared with init= and data
    test = splits.test
    title = f"{test.system_name}: {ckpt['system'].get('system')} checkpoint, no training"
    metrics = score(job, model, test, options, title)
    summary = {
        "task": task,
        "mode": "zeroshot",
        "status": "complete",
        "init": ckpt["path"],
        "trained_on": ckpt["system"].get("system"),
        "system": {"name": test.system_name, "n_nodes": test.n_nodes, "state_names": test.state_names},
        "model": {**model.describe(), "config": job.model_config, **model.report()},
        "data": {
            "n_test": len(test),
            "n_times": test.n_times,
            "dt": test.meta.get("dt"),
            "source": job.data.path or "simulated",
            **data_record(splits),
        },
        "test": metrics,
        "freerun": free_run_scores(job, model, splits.records, options, title),
        "test_error": metrics["rmse"],
        "wall_time": time.perf_counter() - started,
        "run_dir": str(job.runtime.output_dir),
    }
    write_json(job.runtime.output_dir / "summary.json", summary)
    print_summary(f"mpsim {task}: {test.system_name} (zero-shot)", _zero_shot_rows(summary, job, model))
    return summary


def _zero_shot_rows(summary: dict[str, Any], job: Job, model: Model) -> list[tuple[str, str]]:
    splits, metrics = job.splits, summary["test"]
    assert splits is not None
    test, n_file = splits.test, sum(splits.sizes().values())
    rows = [
        ("checkpoint", f"{summary['init']} (trained on {summary['trained_on']})"),
        (
            "evaluated on",
            f"{test.system_name}: {len(test)} test trajectories, N={test.n_nodes}, {test.n_times - 1} steps"
            + (
                f" (the test share of the file's {n_file}; data.split=[0,0,1] evaluates every one)"
                if job.data.from_file and len(test) < n_file
                else ""
            ),
        ),
        ("model", f"{summary['model']['model']} ({summary['model']['n_params']:,} params)"),
        ("test RMSE", f"{fmt(metrics['rmse'])} normalised, {fmt(metrics['rmse_raw'])} raw units"),
        *horizon_rows(metrics),
        *model.report_lines(),
    ]
    if "energy_error" in metrics:
        rows.append(
            (
                "energy error",
                f"{fmt(metrics['energy_error'])} (data's own drift {fmt(metrics['data_energy_drift'], 2)})",
            )
        )
    if metrics.get("n_diverged"):
        rows.append(("diverged", f"{metrics['n_diverged']} of {len(test)} test trajectories"))
    rows += free_run_rows(summary.get("freerun"))
    rows.append(("run dir", str(job.runtime.output_dir)))
    return rows
