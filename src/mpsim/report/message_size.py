"""`layout=message_size`: the MP-NODE paper's Figures 7 and 8, minimum test error against MP-NODE's message size
per system, and the train-loss / test-error curves per message size; L2S runs on the same system are drawn as a
reference."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd

from mpsim.plotting import at_least_a_factor, save_figure, subplots
from mpsim.report.common import (
    LayoutResult,
    by_epoch_row,
    checkpoint_epochs,
    column_key,
    md_table,
    mean_std_count,
    pm,
    read_metrics,
)


def _size_stats(label: str, runs: pd.DataFrame, curves: list[pd.DataFrame]) -> tuple[dict[str, Any], list[Any]]:
    """One message-size table entry (MP-NODE at one size, or L2S) over its seeds: the report.csv fields and the
    Markdown row (min test error, final train loss, epochs_x_min_error, mean ± std)."""
    err, err_sd, n = mean_std_count(runs["min_test_error"])
    exm, exm_sd, _ = mean_std_count(runs["epochs_x_min_error"])
    loss, loss_sd, _ = mean_std_count(pd.Series([float(c["train_loss"].iloc[-1]) for c in curves]))
    stats = {
        "runs": n,
        "min_test_error": err,
        "min_test_error_std": err_sd,
        "epochs_x_min_error": exm,
        "epochs_x_min_error_std": exm_sd,
        "final_train_loss": loss,
        "final_train_loss_std": loss_sd,
    }
    return stats, [label, n, pm(err, err_sd, 3), pm(loss, loss_sd, 3), pm(exm, exm_sd, 4)]


def message_size(frame: pd.DataFrame, out_dir: Path) -> LayoutResult:
    """Figures 7 and 8: MP-NODE's minimum test error and learning curves per message size, per system."""
    train = frame[(frame["task"] == "train") & (frame["mode"] != "zeroshot")].copy()  # zero-shot runs train nothing
    mp = train[(train["model_class"] == "MPNODE") & train["message_size"].notna()]
    if mp.empty:
        return LayoutResult("No MP-NODE training runs found.", pd.DataFrame(), [])
    records, sections = [], []
    systems = sorted(mp["system"].unique(), key=column_key)
    fig, axes = subplots(1, len(systems), figsize=(4.2 * len(systems), 3.4), squeeze=False, layout="constrained")
    cfig, caxes = subplots(2, len(systems), figsize=(4.2 * len(systems), 6.2), squeeze=False, layout="constrained")
    for k, system in enumerate(systems):
        part = mp[mp["system"] == system]
        rows, by_epoch = [], []
        # compared at the quarters of the longest MP-NODE run (L2S may run longer: 10000 epochs against 4000)
        curves = {r: c for r in part["run"] if (c := read_metrics(r)) is not None}  # each metrics.csv read once
        epochs = checkpoint_epochs(list(curves.values()))
        panels = (("train_loss", caxes[0, k]), ("test_error", caxes[1, k]))  # the curves figure's column
        for (m, variant), runs in sorted(
            part.groupby(["message_size", "variant"]), key=lambda kv: (int(kv[0][0]), kv[0][1])
        ):
            loaded = [curves[r] for r in runs["run"] if r in curves]
            label = f"{int(m)}{variant}"
            stats, row = _size_stats(label, runs, loaded)
            records.append({"system": system, "message_size": int(m), "variant": variant.strip(" ()")} | stats)
            rows.append(row)
            if loaded and epochs:
                by_epoch.append(by_epoch_row(label, loaded, epochs))
            for key, ax in panels:
                if loaded:
                    mean = pd.concat([c.set_index("epoch")[key] for c in loaded], axis=1).mean(axis=1).dropna()
                    ax.plot(mean.index, mean.values, label=f"m={label}")
        table = pd.DataFrame([r for r in records if r["system"] == system])
        for variant, vt in table.groupby("variant", sort=False):
            axes[0, k].errorbar(
                vt["message_size"],
                vt["min_test_error"],
                yerr=vt["min_test_error_std"].fillna(0.0),
                marker="o",
                capsize=3,
                label=f"MP-NODE ({variant})" if variant else "MP-NODE",
            )
        l2s_all = train[(train["system"] == system) & (train["model_class"] == "L2S")]
        for variant, l2s in l2s_all.groupby("variant", sort=False):
            name = f"L2S{variant}"
            l2s_curves = [c for c in (read_metrics(r) for r in l2s["run"]) if c is not None]
            stats, row = _size_stats(name, l2s, l2s_curves)
            axes[0, k].axhline(stats["min_test_error"], color="black", linestyle="--", label=name)
            records.append({"system": system, "message_size": None, "model": name} | stats)
            rows.append(row)
            for i, c in enumerate(l2s_curves):  # each seed its own dashed line, named once in the legend
                for key, ax in panels:
                    seed_label = name if i == 0 else None
                    ax.plot(c["epoch"], c[key], color="black", linestyle="--", linewidth=0.8, label=seed_label)
            if l2s_curves and epochs:
                by_epoch.append(by_epoch_row(name, l2s_curves, epochs))
        axes[0, k].set(xlabel="message size", ylabel="min test rollout RMSE", title=system, yscale="log")
        at_least_a_factor(axes[0, k], 4.0)
        axes[0, k].legend(fontsize=8)
        caxes[0, k].set(yscale="log", ylabel="train loss", title=system)
        caxes[1, k].set(yscale="log", xlabel="epoch", ylabel="test rollout RMSE")
        caxes[0, k].legend(fontsize=8)
        sections.append(
            f"**{system}**\n\n"
            + md_table(["message size", "runs", "min test error", "final train loss", "epochs_x_min_error"], rows)
        )
        if by_epoch:  # matched epochs: is the order the same at every stage of training, or only at the end?
            sections.append(
                f"Minimum test error so far, by epoch ({system}; – where a run stopped earlier):\n\n"
                + md_table(["message size", *(f"by epoch {e}" for e in epochs)], by_epoch)
            )
    fig.suptitle("Effect of message size (Figure 8; Figure 7 for quadrotors)")
    cfig.suptitle("Train loss and test error per message size (mean over seeds; L2S dashed black, one line per seed)")
    figures = [save_figure(fig, out_dir / "message_size.png"), save_figure(cfig, out_dir / "message_size_curves.png")]
    return LayoutResult("\n\n".join(sections), pd.DataFrame(records), figures)
