"""`layout=curves`: the MP-NODE paper's Figure 5, test error per epoch of finetuned vs scratch runs (mean over
seeds, min–max band), one panel per target system and training-set size, and the epochs each curve needs to reach
the best error that every curve reaches."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pandas as pd

from mpsim.plotting import save_figure, subplots
from mpsim.report.common import (
    LayoutResult,
    column_key,
    md_table,
    mean_band,
    mixed_units,
    norm_scale,
    read_metrics,
    row_label,
    row_order,
    run_norm_scale,
    target_systems,
)


def curves(frame: pd.DataFrame, out_dir: Path) -> LayoutResult:
    """Figure 5: test error per epoch, finetuned vs scratch, per target system and training-set size."""
    train = frame[(frame["task"] == "train") & frame["mode"].isin(["finetune", "scratch"])].copy()
    if train.empty:
        return LayoutResult("No training runs found.", pd.DataFrame(), [])
    train = train[train["system"].isin(target_systems(train))].copy()
    train["row"] = [row_label(*k) for k in zip(train["model_class"], train["mode"], train["variant"], strict=True)]
    panels = sorted(train.groupby(["system", "n_train"]).groups, key=lambda k: (column_key(k[0]), k[1]))
    n_col = min(3, len(panels))
    n_row = math.ceil(len(panels) / n_col)
    fig, axes = subplots(n_row, n_col, figsize=(4.2 * n_col, 3.2 * n_row), squeeze=False, layout="constrained")
    records, sections = [], []
    for ax, (system, n_train) in zip(axes.flat, panels, strict=False):
        part = train[(train["system"] == system) & (train["n_train"] == n_train)]
        scales = {row: norm_scale(runs) for row, runs in part.groupby("row")}
        raw = mixed_units(scales)  # rows normalised differently: compare them in raw units
        means = {}
        for row, runs in sorted(part.groupby("row"), key=lambda kv: row_order(kv[0])):
            loaded = [
                c.assign(test_error=c["test_error"] * (run_norm_scale(fact) if raw else 1.0))
                for fact in runs.to_dict("records")
                if (c := read_metrics(fact["run"])) is not None
            ]
            if not loaded:
                continue
            wide = mean_band(ax, loaded, "test_error", f"{row} ({len(loaded)})")
            mean = wide.mean(axis=1)
            means[row] = mean
            records += [
                {
                    "system": system,
                    "n_train": n_train,
                    "row": row,
                    "epoch": int(e),
                    "test_error_mean": v,
                    "test_error_std": wide.loc[e].std(),
                    "runs": len(loaded),
                }
                for e, v in mean.items()
            ]
        unit = " (raw units)" if raw else ""
        ax.set(yscale="log", xlabel="epoch", ylabel=f"test rollout RMSE{unit}", title=f"{system}, ds={n_train}")
        ax.legend(fontsize=7)
        section = _reach_table(system, n_train, means)
        if raw:
            stds = ", ".join(f"{row} {v:.3g}" for row, v in sorted(scales.items(), key=lambda kv: row_order(kv[0])))
            section += (
                f"\n\nErrors in raw units (each run's normalised error × its state std): the rows were normalised "
                f"by different stds ({stds})."
            )
        sections.append(section)
    for ax in list(axes.flat)[len(panels) :]:
        ax.axis("off")
    fig.suptitle("Finetuned vs from scratch (mean over seeds, band: min–max)")
    figure = save_figure(fig, out_dir / "curves.png")
    return LayoutResult("\n\n".join(sections), pd.DataFrame(records), [figure])


def _reach_table(system: str, n_train: Any, means: dict[str, pd.Series]) -> str:
    """Epochs each mean curve needs to reach the best error that every curve reaches."""
    trained = {k: v[v.index >= 1] for k, v in means.items() if (v.index >= 1).any()}
    if not trained:
        return f"**{system}, ds={n_train}**: no curves."
    level = max(float(v.min()) for v in trained.values())
    rows = []
    for k, v in trained.items():
        reach = v[v <= level]
        rows.append(
            [
                k,
                f"{float(means[k].iloc[0]):.3g}",
                int(reach.index[0]) if len(reach) else "never",
                f"{float(v.min()):.3g} @ {int(v.idxmin())}",
            ]
        )
    head = f"**{system}, ds={n_train}** — target: {level:.3g}, the best mean test error every curve reaches"
    return head + "\n\n" + md_table(["run", "epoch-0 error", "epochs to target", "min mean error @ epoch"], rows)
