"""`layout=messages`: the MP-NODE paper's Figures 3a and 4, MP-NODE with messages vs `model.zero_messages=true`:
minimum train loss and test error per arm, their ratio, the train loss by matched epochs, and the train-loss /
test-error curves (mean over seeds, min–max band)."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from mpsim.plotting import save_figure, subplots
from mpsim.report.common import (
    LayoutResult,
    by_epoch_row,
    checkpoint_epochs,
    column_key,
    md_table,
    mean_band,
    mean_std_count,
    pm,
    read_metrics,
)


def messages(frame: pd.DataFrame, out_dir: Path) -> LayoutResult:
    """Figures 3a and 4: MP-NODE with messages vs `model.zero_messages=true` (each node an augmented NODE)."""
    train = frame[
        (frame["task"] == "train") & (frame["mode"] != "zeroshot") & (frame["model_class"] == "MPNODE")
    ].copy()
    if train.empty:
        return LayoutResult("No MP-NODE training runs found.", pd.DataFrame(), [])
    train["off"] = train["zero_messages"].map(lambda v: v is True)  # a config without the flag: messages on
    systems = sorted(train["system"].unique(), key=column_key)
    width = max(6.0, 4.2 * len(systems))
    fig, axes = subplots(2, len(systems), figsize=(width, 6.2), squeeze=False, layout="constrained")
    records, sections = [], []
    for k, system in enumerate(systems):
        part = train[train["system"] == system]
        curves = {r: c for r in part["run"] if (c := read_metrics(r)) is not None}  # each metrics.csv read once
        epochs = checkpoint_epochs(list(curves.values()))
        rows, by_epoch, cell = [], [], {}
        # messages on first
        for (off, variant), runs in sorted(part.groupby(["off", "variant"]), key=lambda kv: (bool(kv[0][0]), kv[0][1])):
            label = ("off (`zero_messages=true`)" if off else "on") + variant
            loaded = [curves[r] for r in runs["run"] if r in curves]
            loss = mean_std_count(pd.Series([float(c.loc[c["epoch"] >= 1, "train_loss"].min()) for c in loaded]))
            err = mean_std_count(runs["min_test_error"])
            exm = mean_std_count(runs["epochs_x_min_error"])
            cell[(bool(off), variant)] = (loss[0], err[0])
            records.append(
                {
                    "system": system,
                    "messages": "off" if off else "on",
                    "variant": variant.strip(" ()"),
                    "runs": err[2],
                    "min_train_loss": loss[0],
                    "min_train_loss_std": loss[1],
                    "min_test_error": err[0],
                    "min_test_error_std": err[1],
                    "epochs_x_min_error": exm[0],
                    "epochs_x_min_error_std": exm[1],
                }
            )
            rows.append([label, err[2], pm(*loss[:2], digits=3), pm(*err[:2], digits=3), pm(*exm[:2], digits=4)])
            if loaded and epochs:
                by_epoch.append(by_epoch_row(label, loaded, epochs, "train_loss"))
            colour = "tab:blue" if off else "tab:red"  # the paper's Figure 3a: on red, off blue
            name = ("messages off (zero_messages=true)" if off else "messages on") + variant
            for key, ax in (("train_loss", axes[0, k]), ("test_error", axes[1, k])):
                if loaded:
                    mean_band(ax, loaded, key, f"{name} ({len(loaded)})", colour)
        axes[0, k].set(yscale="log", ylabel="train loss", title=system)
        axes[1, k].set(yscale="log", xlabel="epoch", ylabel="test rollout RMSE")
        axes[0, k].legend(fontsize=7)
        text = f"**{system}**\n\n" + md_table(
            ["messages", "runs", "min train loss", "min test error", "epochs_x_min_error"], rows
        )
        for variant in sorted({v for _, v in cell}):  # on against off, where both ran with the same settings
            if (True, variant) in cell and (False, variant) in cell:
                (loss_on, err_on), (loss_off, err_off) = cell[(False, variant)], cell[(True, variant)]
                holds = loss_on < loss_off and err_on < err_off
                text += (
                    f"\n\nMessages off / on{variant}: train loss {loss_off / loss_on:.3g}×, test error "
                    f"{err_off / err_on:.3g}× — messages {'lower' if holds else 'do NOT lower'} both (the paper's "
                    "Figure 3a: lower training loss with messages on)"
                )
        sections.append(text)
        if by_epoch:  # is the order the same at every stage of training?
            sections.append(
                f"Minimum train loss so far, by epoch ({system}; – where a run stopped earlier):\n\n"
                + md_table(["messages", *(f"by epoch {e}" for e in epochs)], by_epoch)
            )
    fig.suptitle("Messages on vs off (Figure 3a; Figure 4 for Kuramoto): mean over seeds, band min–max")
    return LayoutResult("\n\n".join(sections), pd.DataFrame(records), [save_figure(fig, out_dir / "messages.png")])
