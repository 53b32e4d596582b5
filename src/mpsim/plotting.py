"""Plots people would rather look at than read: learning curves, trajectories with messages, error growth."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from mpsim.files import atomic_write


def subplots(
    nrows: int = 1,
    ncols: int = 1,
    *,
    figsize: tuple[float, float],
    layout: Literal["constrained", "compressed", "tight"] | None = None,
    **kwargs: Any,
) -> tuple[Figure, Any]:
    """`(fig, axes)` as `pyplot.subplots` gives them, on a figure of its own with an Agg canvas: no pyplot, no
    GUI backend and no global figure registry, so plotting never switches the caller's matplotlib backend and
    a figure is freed when it is dropped. `kwargs` go to `Figure.subplots` (`squeeze`, `sharex`, ...)."""
    fig = Figure(figsize=figsize, layout=layout)
    FigureCanvasAgg(fig)
    return fig, fig.subplots(nrows, ncols, **kwargs)


def save_figure(fig: Figure, path: Path) -> Path:
    """Write `fig` as a PNG at `path`, atomically (temp file + rename)."""
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=110, bbox_inches="tight"))
    return path


def at_least_a_factor(ax: Any, factor: float) -> None:
    """Widen a log-scale y axis to span at least `factor` (about the middle of its data): autoscaled, three
    errors 4 % apart fill the panel and read as a large effect."""
    lo, hi = ax.get_ylim()
    if lo > 0 and hi / lo < factor:
        mid = math.sqrt(lo * hi)
        ax.set_ylim(mid / math.sqrt(factor), mid * math.sqrt(factor))


def learning_curves(history: Sequence[dict[str, Any]], path: str | Path, title: str = "") -> Path:
    """Train loss and validation/test rollout error per epoch (log scale)."""
    epochs = [r["epoch"] for r in history]
    fig, (ax_loss, ax_err) = subplots(1, 2, figsize=(10, 3.6))
    train = [(e, r["train_loss"]) for e, r in zip(epochs, history, strict=True) if _finite(r["train_loss"])]
    if train:
        ax_loss.plot(*zip(*train, strict=True), color="tab:gray")
    ax_loss.set(xlabel="epoch", ylabel="train loss", yscale="log", title="training loss")
    for key, colour in (("val_error", "tab:blue"), ("test_error", "tab:red")):
        pts = [(e, r[key]) for e, r in zip(epochs, history, strict=True) if _finite(r[key])]
        if pts:
            ax_err.plot(*zip(*pts, strict=True), color=colour, label=key.replace("_", " "))
    ax_err.set(xlabel="epoch", ylabel="rollout RMSE (normalised)", yscale="log", title="rollout error")
    ax_err.legend()
    if title:
        fig.suptitle(title)
    return save_figure(fig, Path(path))


def trajectories(
    t: torch.Tensor,  # [T] times
    true: torch.Tensor,  # [B, T, N, D] true states
    pred: torch.Tensor,  # [B, T, N, D] predicted states
    path: str | Path,
    state_names: Sequence[str],
    messages: torch.Tensor | None = None,  # [B, T, N, M] MP-NODE messages
    n_traj: int = 2,
    max_nodes: int = 6,
    title: str = "",
) -> Path:
    """Predicted (red) vs observed (blue) states, one column per node, one block of rows per trajectory,
    and the norm of each node's outgoing message (green), like the MP-NODE paper's Figure 2."""
    b, _, n, d = true.shape
    n_traj, nodes = min(n_traj, b), min(n, max_nodes)
    rows_per = d + (1 if messages is not None and messages.shape[-1] > 0 else 0)
    fig, axes = subplots(
        n_traj * rows_per, nodes, figsize=(2.6 * nodes + 1, 1.7 * n_traj * rows_per), squeeze=False, sharex=True
    )
    tt = t.cpu().numpy()
    for i in range(n_traj):
        for k in range(nodes):
            for j in range(d):
                ax = axes[i * rows_per + j, k]
                ax.plot(tt, true[i, :, k, j].cpu().numpy(), color="tab:blue", lw=1.4, label="observed")
                ax.plot(tt, pred[i, :, k, j].cpu().numpy(), color="tab:red", lw=1.1, ls="--", label="predicted")
                if k == 0:
                    ax.set_ylabel(f"traj {i}\n{state_names[j]}")
                if i == 0 and j == 0:
                    ax.set_title(f"node {k}")
            if messages is not None and rows_per > d:
                ax = axes[i * rows_per + d, k]
                ax.plot(tt, messages[i, :, k].norm(dim=-1).cpu().numpy(), color="tab:green", lw=1.2)
                if k == 0:
                    ax.set_ylabel(f"traj {i}\n|message|")
    for ax in axes[-1]:
        ax.set_xlabel("t")
    axes[0, 0].legend(fontsize=7, loc="best")
    if title:
        fig.suptitle(title)
    return save_figure(fig, Path(path))


def error_growth(t: torch.Tensor, per_step: Sequence[float], path: str | Path, title: str = "") -> Path:
    """Rollout RMSE (normalised) against time: how fast predictions drift."""
    fig, ax = subplots(figsize=(5, 3.4))
    if per_step:
        ax.plot(t[: len(per_step)].cpu().numpy(), per_step, color="tab:red")
    ax.set(xlabel="t", ylabel="RMSE (normalised)", title=title or "error growth over the rollout")
    ax.set_yscale("symlog", linthresh=1e-3)
    return save_figure(fig, Path(path))


def _finite(v: Any) -> bool:
    return isinstance(v, int | float) and math.isfinite(v)


def residuals(
    t_mid: torch.Tensor,  # [T−1] step midpoints
    r: torch.Tensor,  # [B, T−1, N, D] one-step residuals
    state_names: Sequence[str],
    path: str | Path,
    n_traj: int = 4,
) -> Path:
    """Residual against time per state variable: a few trajectories (node 0) and the RMS over all."""
    d = r.shape[-1]
    fig, axes = subplots(1, d, figsize=(3.6 * d, 3.2), squeeze=False)
    tt = t_mid.cpu().numpy()
    for k in range(d):
        ax = axes[0, k]
        for i in range(min(n_traj, r.shape[0])):
            ax.plot(tt, r[i, :, 0, k].cpu().numpy(), lw=0.8, alpha=0.7)
        rms = r[..., k].pow(2).nanmean(dim=(0, 2)).sqrt()
        ax.plot(tt, rms.cpu().numpy(), color="black", lw=1.6, label="RMS")
        ax.set(title=f"d{state_names[k]}/dt residual", xlabel="t")
    axes[0, 0].legend(fontsize=7)
    return save_figure(fig, Path(path))


def periodograms(
    spectra: dict[int, tuple[torch.Tensor, torch.Tensor]],  # state index -> ([F] rad/s, [F] power)
    state_names: Sequence[str],
    path: str | Path,
) -> Path:
    """Power of the trajectory-averaged residual against angular frequency, per state variable."""
    fig, ax = subplots(figsize=(5.5, 3.4))
    for k, (freqs, power) in spectra.items():
        ax.semilogy(freqs.cpu().numpy(), power.clamp(min=1e-30).cpu().numpy(), label=state_names[k], lw=1)
    ax.set(xlabel="ω (rad per unit time)", ylabel="power", title="residual periodogram")
    ax.legend()
    return save_figure(fig, Path(path))


def explained_variance(
    explained: dict[str, list[float]],  # candidate label -> share explained alone, per state variable
    state_names: Sequence[str],
    path: str | Path,
    top: int = 8,
) -> Path:
    """Share of the residual each candidate explains on its own (the top few per state variable)."""
    d = len(state_names)
    fig, axes = subplots(1, d, figsize=(4.2 * d, 3.4), squeeze=False)
    for k in range(d):
        items = sorted(((v[k], name) for name, v in explained.items()), reverse=True)[:top]
        ax = axes[0, k]
        ax.barh([n for _, n in items][::-1], [v for v, _ in items][::-1], color="tab:purple")
        ax.set(xlim=(0, 1), title=f"d{state_names[k]}/dt", xlabel="residual explained alone")
        ax.tick_params(axis="y", labelsize=7)
    return save_figure(fig, Path(path))


def error_curves(t: torch.Tensor, curves: dict[str, Sequence[float]], path: str | Path) -> Path:
    """Held-out rollout RMSE against time for several models (e.g. before and after a fix)."""
    fig, ax = subplots(figsize=(5, 3.4))
    for name, values in curves.items():
        if values:
            ax.plot(t[: len(values)].cpu().numpy(), values, label=name)
    ax.set(xlabel="t", ylabel="rollout RMSE (normalised)", title="held-out rollout error")
    ax.set_yscale("symlog", linthresh=1e-3)
    ax.legend()
    return save_figure(fig, Path(path))


def free_run(
    t: torch.Tensor,  # [T] the record's times in its file's clock (s)
    true: torch.Tensor,  # [T, P] the record's measured channels (its length, not padded)
    pred: torch.Tensor,  # [T, P] the free run of the same channels
    names: Sequence[str],
    start: int,
    path: str | Path,
    title: str = "",
    units: Sequence[str] = (),
) -> Path:
    """One test record simulated free: measured and simulated per channel over the whole record, a zoom on the
    stretch of a tenth of the record where they differ most, and the error over time; the samples that started
    the run shaded. `units`: each channel's unit (default: "as recorded")."""
    n, p = true.shape
    fig, axes = subplots(p + 1, 2, figsize=(11, 2.4 * (p + 1)), squeeze=False, layout="constrained")
    err = pred - true
    width = max(2, n // 10)
    for c in range(p):  # a loop over the few channels
        unit = units[c] if c < len(units) else "as recorded"
        label = f"{names[c]} ({unit})"
        worst = int(err[:, c].abs().nan_to_num(nan=0.0).unfold(0, width, 1).mean(-1).argmax()) if n > width else 0
        for ax, (a, b) in ((axes[c, 0], (0, n)), (axes[c, 1], (worst, min(n, worst + width)))):
            ax.plot(t[a:b], true[a:b, c], color="black", lw=0.9, label="measured")
            ax.plot(t[a:b], pred[a:b, c], color="tab:red", lw=0.9, label="simulated (free run)")
            if a < start:  # the samples that started the run
                ax.axvspan(float(t[a]), float(t[min(start, b) - 1]), color="0.85", lw=0, label="start (not scored)")
            ax.set(xlabel="time in the file (s)", ylabel=label)
        axes[c, 0].set_title(f"{names[c]}: whole record" + (f" — {title}" if title and c == 0 else ""))
        axes[c, 1].set_title(f"{names[c]}: zoom where they differ most")
    axes[0, 0].legend(loc="upper right", fontsize=8)
    for c in range(p):
        unit = units[c] if c < len(units) else "as recorded"
        axes[p, 0].plot(t, err[:, c], lw=0.8, label=f"{names[c]} ({unit})")
        axes[p, 1].plot(t, err[:, c].abs().cummax(0).values if n else err[:, c], lw=0.8, label=names[c])
    axes[p, 0].set(xlabel="time in the file (s)", ylabel="simulated − measured", title="free-run error")
    axes[p, 1].set(
        xlabel="time in the file (s)", ylabel="largest |error| so far", title="free-run error, running maximum"
    )
    axes[p, 0].legend(loc="upper right", fontsize=8)
    return save_figure(fig, Path(path))


def effect_against_feature(
    source: torch.Tensor,  # [S] the named effect's source state at each sample (raw units)
    residual: torch.Tensor,  # [S] the model's one-step residual on the effect's row at those samples
    term: torch.Tensor,  # [S] the fitted effect's term at those samples
    xlabel: str,
    ylabel: str,
    path: str | Path,
    title: str = "",
    bins: int = 30,
) -> Path:
    """A partial residual against the named effect's own feature (force against position shows a cubic, against velocity
    a sign change): each sample faint, the mean in `bins` quantile bins of the feature with its standard error (a
    noise-dominated residual averages out there), and the fitted term over the same bins."""
    ok = torch.isfinite(source) & torch.isfinite(residual) & torch.isfinite(term)
    x, r, f = source[ok].double(), residual[ok].double(), term[ok].double()
    fig, ax = subplots(figsize=(5.2, 3.6))
    if x.numel() >= 2 * bins:
        order = torch.argsort(x)
        groups = torch.tensor_split(order, bins)
        xm = torch.stack([x[g].mean() for g in groups]).numpy()  # the few bins
        rm = torch.stack([r[g].mean() for g in groups]).numpy()
        se = torch.stack([r[g].std() / math.sqrt(max(len(g), 1)) for g in groups]).numpy()
        fm = torch.stack([f[g].mean() for g in groups]).numpy()
        step = max(1, x.numel() // 4000)
        ax.scatter(x[::step].numpy(), r[::step].numpy(), s=2, color="0.8", label="partial residual (samples)")
        ax.errorbar(
            xm, rm, yerr=se, fmt="o", ms=3, color="tab:blue", label=f"partial residual, mean of {bins} bins ± se"
        )
        ax.plot(xm, fm, color="tab:red", label="the named effect (fitted)")
        lo, hi = float(min(rm.min() - 3 * se.max(), fm.min())), float(max(rm.max() + 3 * se.max(), fm.max()))
        pad = 0.15 * (hi - lo) if hi > lo else 1.0
        ax.set_ylim(lo - pad, hi + pad)
    ax.set(xlabel=xlabel, ylabel=ylabel, title=title)
    ax.legend(fontsize=7)
    return save_figure(fig, Path(path))
