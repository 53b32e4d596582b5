"""Gene 8x8 at the paper's trainer: lowest test error so far, by epoch, for the finetune from the 4x4 pre-training
stopped at epoch 300 (this folder), the Table 2 finetune from the 4000-epoch pre-training, and scratch.
Run from the repository root: python results/warmstart_paper/compare.py"""

from pathlib import Path

import pandas as pd

RUNS = {
    "finetuned from the 300-epoch pre-training": "results/warmstart_paper/gene/finetune300_ds700_s0",
    "finetuned from the 4000-epoch pre-training (Table 2)": "results/table2_paper/gene/finetune_ds700_s0",
    "scratch (Table 2)": "results/table2_paper/gene/scratch_ds700_s0",
}
EPOCHS = [0, 50, 100, 200, 300, 500, 644, 750, 857, 1000, 1250, 1500, 2000]


def main() -> None:
    curves = {name: pd.read_csv(Path(run) / "metrics.csv").set_index("epoch") for name, run in RUNS.items()}
    last = min(int(c.index.max()) for c in curves.values())
    epochs = [e for e in EPOCHS if e <= last] + ([last] if last not in EPOCHS else [])
    print(f"lowest test error so far (normalised rollout RMSE, 50 steps), by epoch; up to epoch {last}\n")
    print("| run | " + " | ".join(f"{e}" for e in epochs) + " |")
    print("|---|" + "---|" * len(epochs))
    for name, c in curves.items():
        best = c["test_error"].cummin()
        print(f"| {name} | " + " | ".join(f"{best.loc[e]:.4f}" for e in epochs) + " |")
    print("\ntrain loss, by epoch\n")
    print("| run | " + " | ".join(f"{e}" for e in epochs[1:]) + " |")
    print("|---|" + "---|" * len(epochs[1:]))
    for name, c in curves.items():
        print(f"| {name} | " + " | ".join(f"{c['train_loss'].loc[e]:.3f}" for e in epochs[1:]) + " |")
    print(
        "\n| run | epoch of the first halving of the learning rate | train loss spikes (x3 in one epoch) "
        "| test error up by more than 15 % in one epoch (times) |"
    )
    print("|---|---|---|---|")
    for name, c in curves.items():
        c = c.loc[:last]
        halved = c.index[c["lr"] < c["lr"].iloc[0]]
        loss = c["train_loss"]
        spikes = list(c.index[1:][(loss.values[1:] > 3 * loss.values[:-1])])
        test = c["test_error"].values
        jumps = int((test[1:] > 1.15 * test[:-1]).sum())
        print(f"| {name} | {int(halved[0]) if len(halved) else '—'} | {spikes or '—'} | {jumps} |")


if __name__ == "__main__":
    main()
