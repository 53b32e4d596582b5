"""Run directories as `mpsim train` (or a zero-shot run) leaves them, for the report tests, and the report of one
layout over them, made by the library as `mpsim report layout=...` makes it."""

import json
from pathlib import Path

import pandas as pd
import yaml

from mpsim.report import collect, layout_report, unfinished


def fake_run(
    root: Path,
    name: str,
    *,
    system: str,
    mode: str = "scratch",
    model: str = "MPNODE",
    seed: int = 0,
    n_train: int = 100,
    errors: list[float] | None = None,
    message_size: int | None = 3,
    trained_on: str | None = None,
    best_val: float | None = None,
    overrides: list[str] = (),
    device: str | None = None,
    zero_messages: bool | None = None,
    per_step: list[float] | None = None,
    resolved: dict | None = None,
    model_config: dict | None = None,
    state_std: float | None = None,
    exported: str | None = None,
    init: str | None = None,
) -> Path:
    """A run directory as `mpsim train` (or a zero-shot run) leaves it: summary.json, metrics.csv, overrides."""
    run = root / name
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump([f"seed={seed}", *overrides]))
    config = {"_target_": f"mpsim.models.{model}"} | ({"message_size": message_size} if message_size else {})
    config |= {} if zero_messages is None else {"zero_messages": zero_messages}
    config |= model_config or {}
    if resolved is not None:  # the resolved config, as Hydra keeps it
        (run / ".hydra" / "config.yaml").write_text(yaml.safe_dump({"seed": seed} | resolved))
    summary = {
        "task": "train",
        "mode": mode,
        "status": "complete",
        "seed": seed,
        "system": {"name": system, "n_nodes": 10},
        "model": {"model": model, "config": config},
        "data": {"train": n_train, "val": 20, "test": 20, "n_times": 51},
    } | ({"device": device} if device else {})
    if errors is not None:  # a training run: per-epoch curve, Table 2 metric from it
        epochs = list(range(len(errors)))
        pd.DataFrame(
            {"epoch": epochs, "train_loss": [10 * e for e in errors], "val_error": errors, "test_error": errors}
        ).to_csv(run / "metrics.csv", index=False)
        best = min(range(1, len(errors)), key=lambda k: errors[k])
        summary |= {
            "min_test_error": errors[best],
            "min_test_error_epoch": best,
            "epochs_x_min_error": best * errors[best],
            "initial_test_error": errors[0],
            "epochs_run": len(errors) - 1,
            "best_val_error": best_val or errors[best],
            "test": {"rmse": errors[best]},
        }
    else:  # zero-shot evaluation: a test set, no training set
        summary["data"] = {"test": 20, "n_times": 51}
        summary |= {
            "task": "train",
            "mode": "zeroshot",
            "trained_on": trained_on,
            "test": {"rmse": best_val},
            "test_error": best_val,
        }
    summary |= {k: v for k, v in (("exported", exported), ("init", init)) if v is not None}
    if state_std is not None:  # a one-feature system whose states this run normalised by `state_std`
        summary["system"]["state_names"] = ["x"]
        summary["test"]["rmse_raw"] = summary["test"]["rmse"] * state_std
    if per_step is not None:  # test RMSE at each rollout step (index = step), as evaluation records it
        summary["test"]["per_step_rmse"] = per_step
    (run / "summary.json").write_text(json.dumps(summary))
    return run


def report_of(tmp_path: Path, layout: str, runs: Path) -> tuple[dict, Path]:
    """The `layout` report of the runs under `runs`, written to `tmp_path/report_<layout>`: what the library
    returns, and the folder."""
    out = tmp_path / f"report_{layout}"
    out.mkdir(parents=True, exist_ok=True)
    roots = [Path(runs)]
    _, result = layout_report(layout, collect(roots, facts=True), roots, Path.cwd(), out, unfinished(roots))
    return result, out


def table2_runs(root: Path) -> Path:
    """Table 2's runs: a pre-training, finetuned and scratch MP-NODE on lorenz10 (ds 50 and 100) and on gene, L2S
    on gene; seeds 0 and 1."""
    fake_run(root, "pre", system="lorenz3", errors=[2.0, 1.0, 0.8])  # pre-training: not a Table 2 column
    for seed in (0, 1):
        for ds in (50, 100):
            fake_run(
                root,
                f"lf{seed}{ds}",
                system="lorenz10",
                mode="finetune",
                seed=seed,
                n_train=ds,
                errors=[1.0, 0.5, 0.4, 0.45, 0.5],
            )  # min 0.4 at epoch 2 → 0.8
            fake_run(
                root,
                f"ls{seed}{ds}",
                system="lorenz10",
                seed=seed,
                n_train=ds,
                errors=[2.0, 1.5, 1.0, 0.8, 0.6 + 0.1 * seed],
            )  # min at epoch 4 → 2.4 / 2.8
        fake_run(root, f"gf{seed}", system="gene_ba_large", mode="finetune", seed=seed, errors=[0.5, 0.2, 0.1])
        fake_run(root, f"gs{seed}", system="gene_ba_large", seed=seed, errors=[3.0, 1.0, 0.5])
        fake_run(
            root, f"gl{seed}", system="gene_ba_large", model="L2S", seed=seed, message_size=None, errors=[3.0, 2.0, 0.9]
        )
    return root
