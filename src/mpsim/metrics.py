"""Losses and metrics: one vocabulary for every model, and the one module that holds them (training, evaluation,
the residual loop's held-out report and the benchmarks all read their numbers from here).

Errors are computed on full rollouts. "Normalised" means in units of each state feature's standard
deviation over the training split (the model's `state_std`), so errors are comparable across features.
With `features` (the measured columns, `Trajectories.observed_index`) errors are averaged over those features
only: a latent state (estimated, not measured) is not a target.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import torch

from mpsim.periodic import state_difference


def huber_loss(
    pred: torch.Tensor,  # [B, T, N, D] predicted states, normalised units
    target: torch.Tensor,  # [B, T, N, D] true states, normalised units
    delta: float = 1.0,
) -> torch.Tensor:
    """MPNODE.jl's `time_series_huber`: Huber per element, summed over features and steps 1..T−1
    (t0 is given, not predicted), averaged over the B·N node-trajectories."""
    err = pred[:, 1:] - target[:, 1:]
    a = err.abs()
    h = torch.where(a < delta, 0.5 * err.pow(2), delta * (a - 0.5 * delta))
    return h.sum(dim=(1, 3)).mean()


def mse_loss(
    pred: torch.Tensor,  # [B, T, N, D] normalised units
    target: torch.Tensor,  # [B, T, N, D] normalised units
    delta: float = 1.0,
) -> torch.Tensor:
    """Mean squared error over steps 1..T−1, nodes and features."""
    return (pred[:, 1:] - target[:, 1:]).pow(2).mean()


LOSSES: dict[str, Callable[..., torch.Tensor]] = {"huber": huber_loss, "mse": mse_loss}


def select_features(
    x: torch.Tensor,  # [..., D] states (or per-feature values)
    features: Sequence[int] | None,  # the feature columns to keep (None: all)
) -> torch.Tensor:
    """[..., D'] the chosen feature columns of `x` (`x` itself when `features` is None or every column)."""
    if features is None or list(features) == list(range(x.shape[-1])):
        return x
    return x[..., list(features)]


def squared_errors(
    pred: torch.Tensor,  # [B, T, N, D] predicted states, raw units
    target: torch.Tensor,  # [B, T, N, D] true states, raw units
    std: torch.Tensor,  # [D] per-feature scale
    periods: Sequence[float | None] | None = None,  # per feature: period, or None
    features: Sequence[int] | None = None,  # feature columns the errors are on (None: all)
) -> tuple[torch.Tensor, torch.Tensor]:
    """([B, T] mean squared error in normalised units, [B, T] in raw units), averaged over nodes and features
    (the chosen `features` only)."""
    diff = select_features(state_difference(pred, target, periods), features)
    scaled = diff / select_features(std, features)
    return scaled.pow(2).mean(dim=(2, 3)), diff.pow(2).mean(dim=(2, 3))


def rollout_metrics(
    pred: torch.Tensor,  # [B, T, N, D] predicted states, raw units
    target: torch.Tensor,  # [B, T, N, D] true states, raw units
    std: torch.Tensor,  # [D] per-feature scale (training std)
    t: torch.Tensor,  # [T] times
    horizons: Sequence[int] = (),
    periods: Sequence[float | None] | None = None,  # per feature: period of a periodic coordinate, or None
    first: int = 1,
    features: Sequence[int] | None = None,  # feature columns the errors are on (None: all; the measured ones)
) -> dict:
    """Rollout RMSE over steps `first`..T−1 (the steps before `first` were given to the model) and at named
    horizons (steps), in raw and normalised units, over the chosen `features` (a latent state is no target).

    Trajectories whose prediction is not finite count as diverged: they are excluded from the RMSEs and
    counted in ``n_diverged`` (a NaN is a result to report, not a crash).
    """
    finite = torch.isfinite(select_features(pred, features)).flatten(1).all(dim=1)  # [B]
    n_div = int((~finite).sum())
    if finite.sum() == 0:
        nan = math.nan
        return {"rmse": nan, "rmse_raw": nan, "per_step_rmse": [], "horizons": {}, "n_diverged": n_div}
    se_n, se_r = squared_errors(pred[finite], target[finite], std, periods, features)  # [B', T]
    per_step = se_n.mean(0).sqrt()  # [T]
    out: dict[str, Any] = {
        "rmse": float(se_n[:, first:].mean().sqrt()),
        "rmse_raw": float(se_r[:, first:].mean().sqrt()),
        "per_step_rmse": [float(v) for v in per_step],
        "horizons": {},
        "n_diverged": n_div,
    }
    for h in horizons:
        k = min(int(h), pred.shape[1] - 1)
        if k < first:
            continue
        out["horizons"][f"{k}"] = {
            "t": float(t[k] - t[0]),
            "rmse": float(se_n[:, first : k + 1].mean().sqrt()),
            "rmse_raw": float(se_r[:, first : k + 1].mean().sqrt()),
        }
    return out


def relative_energy_error(
    energy: Callable[[torch.Tensor], torch.Tensor],
    pred: torch.Tensor,  # [B, T, N, D] predicted states, raw units
    target: torch.Tensor,  # [B, T, N, D] true states, raw units
) -> dict:
    """Mean |E(pred) − E(true)| / |E(true)| over time and trajectories, and the true data's own drift
    |E(true_t) − E(true_0)| / |E(true_0)| (the floor that no model can beat)."""
    e_pred = energy(pred.to(torch.float64))  # [B, T]
    e_true = energy(target.to(torch.float64))  # [B, T]
    scale = e_true.abs().clamp(min=1e-12)
    rel = ((e_pred - e_true).abs() / scale)[:, 1:]
    rel = rel[torch.isfinite(rel)]
    drift = ((e_true - e_true[:, :1]).abs() / e_true[:, :1].abs().clamp(min=1e-12)).max()
    return {"energy_error": float(rel.mean()) if rel.numel() else math.nan, "data_energy_drift": float(drift)}


def valid_prediction_time(
    pred: torch.Tensor,  # [B, T, N, D] predicted states
    true: torch.Tensor,  # [B, T, N, D] true states
    std: torch.Tensor,  # [D] feature scale
    t: torch.Tensor,  # [T] times
    threshold: float = 0.3,
    features: Sequence[int] | None = None,  # feature columns the error is on (None: all)
) -> float:
    """Mean over trajectories of the time until the normalised RMSE (over nodes and the chosen features) first
    exceeds `threshold` (the whole horizon if it never does)."""
    scaled = select_features((pred - true) / std, features)
    err = scaled.pow(2).mean(dim=(2, 3)).sqrt()  # [B, T]
    err = torch.where(torch.isfinite(err), err, torch.full_like(err, math.inf))
    over = err > threshold
    first = torch.where(over.any(dim=1), over.float().argmax(dim=1), torch.full((err.shape[0],), err.shape[1] - 1))
    return float((t[first] - t[0]).mean())


def relative_mse(u: torch.Tensor, exact: torch.Tensor) -> torch.Tensor:  # u: [T, D, 3], exact: [T, 3]
    """[3] the S-MNN paper's Table 3 metric: relMSE_k = mean_t (û_k − x₀⁽ᵏ⁾)² / Var_t(x₀⁽ᵏ⁾) of the first
    variable's value and derivatives (k = 0, 1, 2)."""
    return ((u[:, 0, :] - exact) ** 2).mean(0) / exact.var(0, unbiased=False)


def epochs_x_min_error(epochs: Sequence[int], errors: Sequence[float]) -> dict:
    """The MP-NODE paper's Table 2 metric: (epoch of the smallest test error) × (that error)."""
    pairs = [(e, v) for e, v in zip(epochs, errors, strict=True) if v == v]  # drop NaN
    if not pairs:
        return {"min_test_error": math.nan, "min_test_error_epoch": None, "epochs_x_min_error": math.nan}
    epoch, err = min(pairs, key=lambda p: (p[1], p[0]))
    return {"min_test_error": err, "min_test_error_epoch": epoch, "epochs_x_min_error": epoch * err}


def first_epoch_below(epochs: Sequence[int], errors: Sequence[float], target: float) -> int | None:
    """First epoch whose error is at or below `target` (None if never)."""
    return next((e for e, v in zip(epochs, errors, strict=True) if v <= target), None)
