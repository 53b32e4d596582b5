"""The process-noise scale when it is unknown: the multiplier of a given Q shape under which the measurements are
most likely (the sum over records of the filter's log-likelihood), found on a short grid and refined once."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from mpsim.errors import DataError, DivergenceError
from mpsim.estimate.kalman import Smoothed, kalman_smoother
from mpsim.estimate.linearise import Map

# decades from 1e-4 to 1e4 of the Q shape given: 9 smoother runs, then 5 more to refine about the best
DEFAULT_GRID = tuple(10.0**e for e in range(-4, 5))


@dataclass
class ProcessNoiseChoice:
    """The chosen scale of Q, the smoothed result under it, and every scale tried with its log-likelihood.

    Example::

        choice = choose_process_noise(step, output, y, x0, P0, Q, R)
        choice.scale, choice.smoothed.mean  # the multiplier of Q; [B, T, D] under scale · Q
    """

    scale: float
    smoothed: Smoothed
    scales: Tensor  # [G] every scale tried, in the order tried (the grid, then the refinement)
    log_likelihood: Tensor  # [G] the summed log-likelihood of all records under each
    at_edge: bool  # the best grid point was the grid's smallest or largest: widen the grid


def _vertex(x: Sequence[float], f: Sequence[float]) -> float | None:
    """The maximiser of the parabola through three points (x ascending), if it is a maximum inside their span."""
    (x0, x1, x2), (f0, f1, f2) = x, f
    d1, d2 = (f1 - f0) / (x1 - x0), (f2 - f1) / (x2 - x1)
    curvature = (d2 - d1) / (x2 - x0)
    if not curvature < 0:
        return None
    vertex = 0.5 * (x0 + x1) - d1 / (2 * curvature)
    return vertex if x0 < vertex < x2 else None


def choose_process_noise(
    step: Map,
    output: Map,
    y: Tensor,
    x0: Tensor,
    P0: Tensor,
    Q: Tensor,
    R: Tensor,
    method: str = "ekf",
    iterations: int = 1,
    grid: Sequence[float] = DEFAULT_GRID,
    refine: int = 2,
) -> ProcessNoiseChoice:
    """The scale s of the process noise s·Q that maximises the measurements' log-likelihood, summed over records.

    Runs `kalman_smoother` once per grid value (default: the decades 1e-4 … 1e4); then `refine` times twice more, at
    the geometric midpoints between the best scale so far and its two neighbours (each round halves the spacing in
    log10 s: ±0.5, then ±0.25 decade); then once at the maximum of the parabola in log10 s through the best scale and
    its neighbours. It keeps the best of all (9 + 2·2 + 1 = 14 runs by default). A scale whose run fails (a sigma point
    outside the model's domain, NaN) is skipped, and only if all fail is the error raised. A best grid value at the grid's edge
    is not refined and sets `at_edge`. The arguments are those of `kalman_smoother`; `Q: [D, D] or [B, D, D]` gives
    the shape (the relative sizes and correlations of the process noise), the grid its scale.

    Returns:
        A `ProcessNoiseChoice`: the scale, the smoothed result under it, and each scale tried with its log-likelihood.

    Example (with `kalman_smoother`'s example's arguments)::

        choice = choose_process_noise(step, output, y, x0, P0, torch.eye(2), R, grid=[1e-3, 1e-2, 1e-1, 1.0])
        choice.scale, choice.at_edge  # the multiplier of torch.eye(2); whether the grid should be widened
    """
    values = sorted(float(s) for s in grid)
    if len(values) < 1 or values[0] <= 0:
        raise DataError(f"grid must hold positive scales (got {list(grid)}).")
    Q = torch.as_tensor(Q)
    runs: dict[float, tuple[Smoothed, float]] = {}
    failed: dict[float, str] = {}

    def run(scale: float) -> None:
        try:
            smoothed = kalman_smoother(step, output, y, x0, P0, scale * Q, R, method, iterations)
        except DivergenceError as err:  # e.g. sigma points outside the model's domain (sqrt of a level below 0)
            failed[scale] = str(err)
            return
        runs[scale] = (smoothed, float(smoothed.log_likelihood.sum()))

    def best_three() -> tuple[list[float], int]:
        tried = sorted(runs)
        best = max(range(len(tried)), key=lambda i: runs[tried[i]][1])
        return tried[max(best - 1, 0) : best + 2], best

    for scale in values:
        run(scale)
    if not runs:
        first = next(iter(failed.values()))
        raise DivergenceError(f"the smoother failed at every process-noise scale tried ({first})")
    values = [v for v in values if v in runs]
    _, best = best_three()
    at_edge = len(values) > 1 and best in (0, len(values) - 1)
    for _ in range(refine if not at_edge and len(values) > 2 else 0):
        (low, mid, high), _ = best_three()
        run(math.sqrt(low * mid))
        run(math.sqrt(mid * high))
    around, _ = best_three()
    if not at_edge and len(around) == 3:
        vertex = _vertex([math.log10(s) for s in around], [runs[s][1] for s in around])
        if vertex is not None:
            run(10.0**vertex)
    chosen = max(runs, key=lambda s: runs[s][1])
    return ProcessNoiseChoice(
        scale=chosen,
        smoothed=runs[chosen][0],
        scales=torch.tensor(list(runs), dtype=torch.float64),
        log_likelihood=torch.tensor([r[1] for r in runs.values()], dtype=torch.float64),
        at_edge=at_edge,
    )
