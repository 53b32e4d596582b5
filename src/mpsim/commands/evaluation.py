"""Evaluating a model on a test split: metrics, plots, and the summary of a checkpoint evaluated without
training. Shared by `mpsim eval` and `mpsim train` (its final test, and `mode=zeroshot`)."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

from mpsim import plotting
from mpsim.commands.building import build_system, model_and_data
from mpsim.commands.checkpoints import load_init
from mpsim.commands.runtime import Runtime
from mpsim.console import fmt, print_summary
from mpsim.data.io import save_npz
from mpsim.data.trajectories import Trajectories
from mpsim.files import write_json
from mpsim.metrics import relative_energy_error, rollout_metrics
from mpsim.models.base import Model
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
        pred, true, std, test.t, horizons, periods=test.meta.get("periods"), first=model.context_steps
    )
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


def evaluate_checkpoint(cfg: DictConfig, rt: Runtime, task: str) -> dict:
    """Shared by `mpsim eval` and `mpsim train mode=zeroshot`."""
    t0 = time.perf_counter()
    ckpt = load_init(cfg, rt)
    assert ckpt is not None  # both callers require init= (`mpsim eval`, `resolve_mode` for zeroshot)
    system = None if cfg.data.path and cfg.data.graph != "system" else build_system(cfg)
    # nothing trains: a file's train and val shares may be zero (data.split=[0,0,1] evaluates every trajectory)
    model, model_cfg, splits = model_and_data(cfg, rt, system, ckpt, refit=False, need=("test",))
    test = splits.test
    n_file = sum(splits.sizes().values())
    title = f"{test.system_name}: {ckpt['system'].get('system')} checkpoint, no training"
    metrics = evaluate_model(
        model,
        test,
        rt.output_dir,
        list(cfg.eval.horizons),
        None if cfg.data.path else system,
        cfg.eval.n_plot,
        cfg.eval.plots,
        title,
        cfg.eval.save_predictions,
    )
    summary = {
        "task": task,
        "mode": "zeroshot",
        "status": "complete",
        "init": ckpt["path"],
        "trained_on": ckpt["system"].get("system"),
        "system": {"name": test.system_name, "n_nodes": test.n_nodes, "state_names": test.state_names},
        "model": {**model.describe(), "config": model_cfg, **model.report()},
        "data": {
            "n_test": len(test),
            "n_times": test.n_times,
            "dt": test.meta.get("dt"),
            "source": cfg.data.path or "simulated",
        },
        "test": metrics,
        "test_error": metrics["rmse"],
        "wall_time": time.perf_counter() - t0,
        "run_dir": str(rt.output_dir),
    }
    write_json(rt.output_dir / "summary.json", summary)
    rows = [
        ("checkpoint", f"{ckpt['path']} (trained on {summary['trained_on']})"),
        (
            "evaluated on",
            f"{test.system_name}: {len(test)} test trajectories, N={test.n_nodes}, {test.n_times - 1} steps"
            + (
                f" (the test share of the file's {n_file}; data.split=[0,0,1] evaluates every one)"
                if cfg.data.path and len(test) < n_file
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
    rows.append(("run dir", str(rt.output_dir)))
    print_summary(f"mpsim {task}: {test.system_name} (zero-shot)", rows)
    return summary
