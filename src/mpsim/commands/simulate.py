"""`mpsim simulate system=<name> [init=<ckpt>] format=npz|csv|both`: export ground-truth trajectories and,
with `init=`, the model's rollout from the same initial states."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

from mpsim import plotting
from mpsim.commands.building import Shape
from mpsim.commands.guards import check_simulation_memory
from mpsim.commands.prepare import Job, prepare
from mpsim.commands.runtime import given
from mpsim.console import fmt, print_summary
from mpsim.data.dataset import generate
from mpsim.data.io import save_csv, save_npz
from mpsim.data.trajectories import Trajectories
from mpsim.errors import ConfigError
from mpsim.files import write_json
from mpsim.metrics import rollout_metrics
from mpsim.models.rollout import rollout

log = logging.getLogger(__name__)

FORMATS = ("npz", "csv", "both")


def _export(traj: Trajectories, stem: Path, fmt_name: str) -> list[str]:
    written = []
    if fmt_name in ("npz", "both"):
        written.append(str(save_npz(traj, stem.with_suffix(".npz"))))
    if fmt_name in ("csv", "both"):
        written += [str(p) for p in save_csv(traj, stem.with_suffix(".csv"))]
    return written


def run_simulate(cfg: DictConfig, output_dir: str | Path | None = None, overrides: list[str] | None = None) -> dict:
    """Simulate `n` trajectories of `system=` (seed `data.seed`) and export them (and a model's rollout)."""
    if cfg.format not in FORMATS:
        raise ConfigError(f"format={cfg.format!r} is unknown; choose one of {', '.join(FORMATS)}.")
    if cfg.n < 1:
        raise ConfigError(f"n must be >= 1; got {cfg.n}.")
    job = prepare(cfg, "simulate", output_dir, overrides, with_data=False)
    if given(job.runtime.overrides, "seed"):
        # `seed` is train's seed (weights, batches); the trajectories come from data.seed, as in train
        raise ConfigError(
            f"seed={cfg.seed} does not choose the trajectories of mpsim simulate: their initial states are drawn "
            f"with data.seed (now {cfg.data.seed}), as train draws its dataset. Pass data.seed={cfg.seed} instead."
        )
    truth = simulate_truth(job, int(cfg.n))
    summary, rows = export_truth(job, truth, str(cfg.out), str(cfg.format))
    if job.checkpoint is not None:
        rows += export_model(job, truth, str(cfg.out), str(cfg.format), summary)
    else:
        plot_truth(job, truth, truth.x, "ground truth")
    write_json(job.runtime.output_dir / "summary.json", summary)
    rows += [
        ("files", "\n".ljust(16).join(summary["files"] + summary.get("model_files", []))),
        ("run dir", str(job.runtime.output_dir)),
    ]
    print_summary(f"mpsim simulate: {summary['system']}", rows)
    return summary


def simulate_truth(job: Job, n: int) -> Trajectories:
    """`n` trajectories of the job's system, drawn with `data.seed` as train draws its dataset."""
    system, data = job.system, job.data
    assert system is not None  # simulate always builds its system
    burn_in = int(data.burn_in)  # as train simulates its dataset
    check_simulation_memory(system, [n], burn_in + int(data.horizon or system.horizon) + 1, job.runtime.memory_check)
    return generate(
        system,
        n,
        data.seed,
        dt=data.dt,
        horizon=data.horizon,
        rtol=data.gt_rtol,
        atol=data.gt_atol,
        **({"burn_in": burn_in} if burn_in else {}),  # only systems that support it are asked for it
    )


def export_truth(
    job: Job, truth: Trajectories, out: str, fmt_name: str
) -> tuple[dict[str, Any], list[tuple[str, str]]]:
    """Write the ground truth; (the summary so far, the summary box's rows)."""
    assert job.system is not None
    files = _export(truth, job.runtime.output_dir / out, fmt_name)
    summary = {
        "task": "simulate",
        "system": job.system.name,
        "n": len(truth),
        "n_times": truth.n_times,
        "dt": truth.meta.get("dt"),
        "files": files,
        "run_dir": str(job.runtime.output_dir),
    }
    return summary, [("system", repr(job.system)), ("trajectories", f"{len(truth)} × {truth.n_times} time points")]


def export_model(
    job: Job, truth: Trajectories, out: str, fmt_name: str, summary: dict[str, Any]
) -> list[tuple[str, str]]:
    """The `init=` model's rollout from the truth's initial states: written, scored and drawn beside the truth."""
    ckpt = job.checkpoint
    assert ckpt is not None
    model = job.build_model(Shape.of(truth), ckpt)
    pred, aux = rollout(model, truth, aux=True)
    model_traj = Trajectories(
        t=truth.t, x=pred.double(), edge_index=truth.edge_index, u=truth.u, meta={**truth.meta, "model": ckpt["path"]}
    )
    summary["model_files"] = _export(model_traj, job.runtime.output_dir / f"{out}_model", fmt_name)
    metrics = rollout_metrics(pred, truth.x.to(pred.dtype), model.state_std.cpu().to(pred.dtype), truth.t)
    summary["model_rmse"] = metrics["rmse"]
    summary["model_rmse_raw"] = metrics["rmse_raw"]
    plot_truth(job, truth, pred, f"truth vs {Path(ckpt['path']).name}", aux.get("messages"))
    return [
        ("model", f"{ckpt['path']}: rollout RMSE {fmt(metrics['rmse'])} normalised, {fmt(metrics['rmse_raw'])} raw")
    ]


def plot_truth(job: Job, truth: Trajectories, pred: torch.Tensor, what: str, messages: Any = None) -> None:
    """The first (up to) three trajectories: the truth, and `pred` over it."""
    assert job.system is not None
    plotting.trajectories(
        truth.t,
        truth.x,
        pred,
        job.runtime.output_dir / "plots" / "trajectories.png",
        truth.state_names,
        messages=messages,
        n_traj=min(len(truth), 3),
        title=f"{job.system.name}: {what}",
    )
