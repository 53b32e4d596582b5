"""`mpsim simulate system=<name> [init=<ckpt>] format=npz|csv|both`: export ground-truth trajectories and,
with `init=`, the model's rollout from the same initial states."""

from __future__ import annotations

import logging
from pathlib import Path

from omegaconf import DictConfig

from mpsim import plotting
from mpsim.commands.building import Shape, build_model_for, build_system
from mpsim.commands.checkpoints import load_init
from mpsim.commands.runtime import setup_runtime
from mpsim.commands.splits import check_simulation_memory
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
    rt = setup_runtime(cfg, output_dir, overrides)
    if cfg.format not in FORMATS:
        raise ConfigError(f"format={cfg.format!r} is unknown; choose one of {', '.join(FORMATS)}.")
    if cfg.n < 1:
        raise ConfigError(f"n must be >= 1; got {cfg.n}.")
    if any(a.split("=", 1)[0].lstrip("+~") == "seed" for a in rt.overrides):
        # `seed` is train's seed (weights, batches); the trajectories come from data.seed, as in train
        raise ConfigError(
            f"seed={cfg.seed} does not choose the trajectories of mpsim simulate: their initial states are drawn "
            f"with data.seed (now {cfg.data.seed}), as train draws its dataset. Pass data.seed={cfg.seed} instead."
        )
    system = build_system(cfg)
    burn_in = int(cfg.data.burn_in)  # as train simulates its dataset (it was ignored here)
    check_simulation_memory(cfg, system, [cfg.n], burn_in + int(cfg.data.horizon or system.horizon) + 1)
    truth = generate(
        system,
        cfg.n,
        cfg.data.seed,
        dt=cfg.data.dt,
        horizon=cfg.data.horizon,
        rtol=cfg.data.gt_rtol,
        atol=cfg.data.gt_atol,
        **({"burn_in": burn_in} if burn_in else {}),  # only systems that support it are asked for it
    )
    stem = rt.output_dir / cfg.out
    files = _export(truth, stem, cfg.format)
    summary = {
        "task": "simulate",
        "system": system.name,
        "n": cfg.n,
        "n_times": truth.n_times,
        "dt": truth.meta.get("dt"),
        "files": files,
        "run_dir": str(rt.output_dir),
    }
    rows = [("system", repr(system)), ("trajectories", f"{cfg.n} × {truth.n_times} time points")]
    ckpt = load_init(cfg, rt)
    if ckpt is not None:
        model, _ = build_model_for(cfg, rt, Shape.of(truth), ckpt)
        pred, aux = rollout(model, truth, aux=True)
        model_traj = Trajectories(
            t=truth.t,
            x=pred.double(),
            edge_index=truth.edge_index,
            u=truth.u,
            meta={**truth.meta, "model": ckpt["path"]},
        )
        summary["model_files"] = _export(model_traj, rt.output_dir / f"{cfg.out}_model", cfg.format)
        metrics = rollout_metrics(pred, truth.x.to(pred.dtype), model.state_std.cpu().to(pred.dtype), truth.t)
        summary["model_rmse"] = metrics["rmse"]
        summary["model_rmse_raw"] = metrics["rmse_raw"]
        plotting.trajectories(
            truth.t,
            truth.x,
            pred,
            rt.output_dir / "plots" / "trajectories.png",
            truth.state_names,
            messages=aux.get("messages"),
            n_traj=min(cfg.n, 3),
            title=f"{system.name}: truth vs {Path(ckpt['path']).name}",
        )
        rows.append(
            ("model", f"{ckpt['path']}: rollout RMSE {fmt(metrics['rmse'])} normalised, {fmt(metrics['rmse_raw'])} raw")
        )
        files = files + summary["model_files"]
    else:
        plotting.trajectories(
            truth.t,
            truth.x,
            truth.x,
            rt.output_dir / "plots" / "trajectories.png",
            truth.state_names,
            n_traj=min(cfg.n, 3),
            title=f"{system.name}: ground truth",
        )
    write_json(rt.output_dir / "summary.json", summary)
    rows += [("files", "\n".ljust(16).join(files)), ("run dir", str(rt.output_dir))]
    print_summary(f"mpsim simulate: {system.name}", rows)
    return summary
