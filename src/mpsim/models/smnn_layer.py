"""The MNN layer of S-MNN discovery and the windows it trains on.

`solve_linear_ode` is the least-squares ODE layer with any of the solvers (the linear-time S-MNN solves, the
same system with a dense Cholesky, or the original MNN); the window helpers draw the training windows, their
time steps and their observed past (for delayed effects).
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from mpsim.errors import ConfigError
from mpsim.solvers.mnn_dense import dense_solve, mnn_dense_solve
from mpsim.solvers.smnn import METHODS, smnn_solve

LAYER_METHODS = (*METHODS, "dense", "mnn")


def solve_linear_ode(
    coefficients: torch.Tensor,  # [*batch, T or 1, E, D, O] equation coefficients
    rhs: torch.Tensor,  # [*batch, T, E] equation right-hand sides
    init: torch.Tensor,  # [*batch, 1, D, I] initial values at the first step
    steps: torch.Tensor | float,  # [*batch, T-1] or one shared step
    method: str,
) -> torch.Tensor:  # [*batch, T, D, O]
    """The MNN layer: least-squares solution of a linear ODE with any of the solvers.

    "banded"/"cyclic"/"auto" are the linear-time S-MNN solves, "dense" the same S-MNN system with a dense
    Cholesky, "mnn" the original MNN with a slack variable and central smoothness rows (spec §6.1).
    """
    if method == "dense":
        return dense_solve(coefficients, rhs, init, steps)
    if method == "mnn":
        return mnn_dense_solve(coefficients, rhs, init, steps)[0]
    return smnn_solve(coefficients, rhs, init, steps, method=method)


def uniform_step(t: torch.Tensor) -> float | None:  # t: [T] times
    """The grid's step when `t` is uniform (to 1e-6 relative), else None."""
    dt = t[1:] - t[:-1]
    return float(dt[0]) if bool(((dt - dt[0]).abs() <= 1e-6 * dt[0].abs()).all()) else None


def sample_windows(
    x: torch.Tensor,  # [B, T, N, D] trajectories
    n_windows: int,
    length: int,
    generator: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # [M, W, N, D] windows, [M] trajectory, [M] start
    """`n_windows` random windows of `length` consecutive steps (uniform over trajectory and start)."""
    traj = torch.randint(x.shape[0], (n_windows,), generator=generator).to(x.device)
    start = torch.randint(x.shape[1] - length + 1, (n_windows,), generator=generator).to(x.device)
    steps = start[:, None] + torch.arange(length, device=x.device)
    return x[traj[:, None], steps], traj, start


def window_history(
    x: torch.Tensor,  # [B, T, N, D] the batch's observed trajectories
    t: torch.Tensor,  # [T] their times
    traj: torch.Tensor,  # [M] trajectory of each window
    length: int,  # W
) -> Callable[[torch.Tensor], torch.Tensor]:
    """history(t_query [M·W, 1]) -> [M·W, N, D]: each window point's trajectory at earlier times, linearly
    interpolated on the observed grid, constant before its first state (as the delay integrator's)."""
    dt = uniform_step(t)
    if dt is None:
        raise ConfigError("SMNNDiscovery trains delayed effects on uniform time grids only.")
    rows = traj[:, None].expand(-1, length).reshape(-1)  # [M·W]

    def history(t_query: torch.Tensor) -> torch.Tensor:  # t_query: [M·W, 1]
        pos = ((t_query[:, 0] - t[0]) / dt).clamp(0, x.shape[1] - 1)
        lo = pos.floor().long()
        hi = (lo + 1).clamp(max=x.shape[1] - 1)
        frac = (pos - lo.to(pos))[:, None, None].to(x)
        return x[rows, lo] * (1 - frac) + x[rows, hi] * frac

    return history
