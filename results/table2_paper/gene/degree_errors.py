"""Per-node test error by in-degree: Table 2's gene 8x8 finetuned and scratch MP-NODE runs (seed 0).

Asks whether the finetune's excess error sits at the in-degrees its gene 4x4 pre-training never saw. Reads the
test split and each model's rollout written by `mpsim eval ... eval.save_predictions=true` (commands in
degree_errors.md) and prints a markdown table. Usage: python degree_errors.py <eval dir of finetune> <of scratch>
<of the pre-trained model on gene_ba_small>
"""

import sys

import numpy as np


def in_degrees(edge_index: np.ndarray, n: int) -> np.ndarray:  # edge_index: [B, 2, E] padded with -1
    """[B, N] in-degree of every node of every trajectory's graph."""
    b = edge_index.shape[0]
    dst = edge_index[:, 1]
    rows = np.broadcast_to(np.arange(b)[:, None], dst.shape)
    keep = dst >= 0
    return np.bincount(rows[keep] * n + dst[keep], minlength=b * n).reshape(b, n)


def main(finetune: str, scratch: str, pre: str) -> None:
    test = np.load(f"{finetune}/test.npz")
    x = test["x"][:, 1:, :, 0]  # [B, T, N] truth over steps 1..T
    deg = in_degrees(test["edge_index"], x.shape[2])
    pre_test = np.load(f"{pre}/test.npz")
    pre_deg = in_degrees(pre_test["edge_index"], pre_test["x"].shape[2])
    std = 13.813  # both runs' state std (the gene 8x8 training data's): errors in their normalised units
    err = {}
    for name, run in (("finetuned", finetune), ("scratch", scratch)):
        pred = np.load(f"{run}/test_model.npz")["x"][:, 1:, :, 0]
        err[name] = np.sqrt(((pred - x) ** 2).mean(axis=1)) / std  # [B, N] per-node RMSE over time
    print(
        f"pre-training graphs (gene 4x4, BA(16, 8)) in-degree: {pre_deg.min()}-{pre_deg.max()}, "
        f"median {np.median(pre_deg):g}; target graphs (gene 8x8, BA(64, 32)): {deg.min()}-{deg.max()}, "
        f"median {np.median(deg):g}\n"
    )
    print("| in-degree | node-trajectories | finetuned | scratch | finetuned / scratch |\n|---|---|---|---|---|")
    edges = [0, 8, 16, 24, 32, 40, 48, 64]
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        m = (deg >= lo) & (deg < hi)
        if m.any():
            f, s = (float(np.sqrt((err[k][m] ** 2).mean())) for k in ("finetuned", "scratch"))
            print(f"| {lo}-{hi - 1} | {int(m.sum())} | {f:.4f} | {s:.4f} | {f / s:.2f} |")
    f, s = (float(np.sqrt((err[k] ** 2).mean())) for k in ("finetuned", "scratch"))
    print(f"| all | {deg.size} | {f:.4f} | {s:.4f} | {f / s:.2f} |\n")
    excess = err["finetuned"] - err["scratch"]
    print(
        f"correlation with in-degree: finetuned error {np.corrcoef(err['finetuned'].ravel(), deg.ravel())[0, 1]:.3f}, "
        f"scratch error {np.corrcoef(err['scratch'].ravel(), deg.ravel())[0, 1]:.3f}, "
        f"the finetune's excess {np.corrcoef(excess.ravel(), deg.ravel())[0, 1]:.3f}"
    )


if __name__ == "__main__":
    main(*sys.argv[1:4])
