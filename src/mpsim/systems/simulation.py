"""`simulate`: ground-truth trajectories of a `System`, as `mpsim simulate` and `mpsim train` draw them."""

from __future__ import annotations

from typing import Any

from mpsim.data.dataset import generate
from mpsim.data.trajectories import Trajectories
from mpsim.systems.base import System


def simulate(
    system: System,
    n: int,
    *,
    seed: int = 0,
    dt: float | None = None,
    horizon: int | None = None,
    burn_in: int = 0,
    rtol: float = 1e-8,
    atol: float = 1e-10,
) -> Trajectories:
    """`n` trajectories of `system` from initial states drawn with `seed`, sampled every `dt` for `horizon` steps.

    The same draw as `mpsim simulate system=<name> n=<n> data.seed=<seed>` with the same `data.dt`,
    `data.horizon`, `data.burn_in`, `data.gt_rtol` and `data.gt_atol` (whose defaults these are); `mpsim train`
    draws its three splits with seeds 3s, 3s+1 and 3s+2 for `data.seed=s`.

    Args:
        system: the ground truth (`mpsim.systems`: `CoupledPendulums`, `CoupledLorenz`, `NBody`, ...).
        n: number of trajectories.
        seed: seed of the initial states.
        dt: sampling step in the system's time units (None: the system's `dt`).
        horizon: steps per trajectory, so T = horizon + 1 time points (None: the system's `horizon`).
        burn_in: steps simulated first and dropped (e.g. to start on a chaotic attractor); the recorded times
            keep the clock running. Only systems that support it may be given a nonzero value.
        rtol, atol: tolerances of the adaptive ground-truth solver (fixed-step systems ignore them).

    Returns:
        `Trajectories` with `t: [T]`, `x: [n, T, N, D]` (float64) and the system's graph and metadata.

    Raises:
        ConfigError: bad sizes, or dynamics that cannot be simulated at these settings (named with the system).

    Examples:
        >>> from mpsim import simulate
        >>> from mpsim.systems import CoupledPendulums
        >>> data = simulate(CoupledPendulums(), 3, seed=1, horizon=5)
        >>> len(data), data.n_times, data.state_dim
        (3, 6, 2)
    """
    extra: dict[str, Any] = {"burn_in": burn_in} if burn_in else {}  # only systems that support it are asked
    return generate(system, n, seed, dt=dt, horizon=horizon, rtol=rtol, atol=atol, **extra)
