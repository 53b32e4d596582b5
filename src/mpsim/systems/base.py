"""`System`: the true dynamics of a graph of identical nodes, and how to sample data from it.

A system is vectorised over a batch of trajectories: `rhs(t, x)` takes x [B, N, D] and returns dx/dt of
the same shape. Ground truth is integrated in float64 with an adaptive solver (`simulate`). Systems whose
ground truth is not a plain ODE (a symplectic N-body integrator, a closed-loop controller) override
`simulate`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch
from torchdiffeq import odeint

from mpsim.data.trajectories import Trajectories, grid_step
from mpsim.effects import EffectContext, min_delay, total
from mpsim.errors import ConfigError
from mpsim.solvers.dde import delay_substeps, rk4_delay
from mpsim.solvers.odeint import ADAPTIVE

#: adaptive ground-truth steps allowed per sampling interval (the seed systems take 1–5 at their defaults): a
#: sampling step far too long for the dynamics (`data.dt` in the wrong units) ends with a message, not a hang
GROUND_TRUTH_MAX_STEPS = 20_000


def check_fixed_steps(name: str, n_steps: int, interval: float, system_dt: float) -> None:
    """Refuse a fixed-step ground truth that needs more than GROUND_TRUTH_MAX_STEPS steps per sampling interval:
    `n_steps` steps for an interval of `interval` (`data.dt`); `system_dt` is the system's own sampling step."""
    if n_steps > GROUND_TRUTH_MAX_STEPS:
        raise ConfigError(
            f"cannot simulate {name}: one sampling interval of {interval:g} needs {n_steps:.3g} integrator steps "
            f"(at most {GROUND_TRUTH_MAX_STEPS}), so data.dt is far too long for this system (its own step is "
            f"{system_dt:g}). Set data.dt in the system's time units, e.g. data.dt={system_dt:g}."
        )


class System:
    """True dynamics of `n_nodes` identical subsystems coupled on a graph.

    Subclasses set the class attributes below and implement `dynamics` and `sample_initial_states`.

    Class attributes:
        state_names: names of the D per-node state variables (also the CSV column names).
        control_names: names of the C per-node controls (empty when the system has none).
        dt: default sampling step of generated datasets.
        horizon: default number of steps per generated trajectory (T = horizon + 1 points).

    Args:
        name: the name datasets and exported checkpoints carry (e.g. ``lorenz3``).
        n_nodes: N, the number of subsystems.
        edge_index: [2, E] (sender, receiver) coupling graph.
        effects: extra named terms added to the right-hand side (see `mpsim.effects`).

    Examples:
        Three nodes that each decay as dx/dt = -x, simulated for one time unit:

        >>> import math, torch
        >>> from mpsim import System, simulate
        >>> class Decay(System):
        ...     state_names = ("x",)
        ...     dt, horizon = 0.1, 10
        ...     def __init__(self):
        ...         super().__init__("decay", 3, torch.tensor([[0, 1], [1, 2]]))
        ...     def dynamics(self, t, x, u=None):
        ...         return -x
        ...     def sample_initial_states(self, n, generator):
        ...         return torch.rand(n, self.n_nodes, 1, generator=generator, dtype=torch.float64)
        >>> data = simulate(Decay(), 2)
        >>> tuple(data.x.shape)
        (2, 11, 3, 1)
        >>> bool(torch.allclose(data.x[:, -1], data.x[:, 0] * math.exp(-1.0)))
        True
    """

    state_names: tuple[str, ...] = ()
    control_names: tuple[str, ...] = ()
    dt: float = 0.1
    horizon: int = 50

    def __init__(self, name: str, n_nodes: int, edge_index: torch.Tensor, effects: Sequence[Any] = ()) -> None:
        self.name = name
        self.n_nodes = int(n_nodes)
        self.edge_index = edge_index
        self.effects = [e.bind(self.state_names) for e in effects]
        self._contexts: dict[tuple, EffectContext] = {}

    # ---- facts ---------------------------------------------------------------------------------------

    @property
    def state_dim(self) -> int:
        return len(self.state_names)

    @property
    def control_dim(self) -> int:
        return len(self.control_names)

    def params(self) -> dict[str, Any]:
        """Physical parameters as plain JSON-able values (stored in data and checkpoint metadata)."""
        return {}

    def meta(self, dt: float) -> dict[str, Any]:
        """Metadata carried by every `Trajectories` this system generates."""
        return {
            "system": self.name,
            "system_class": f"{type(self).__module__}.{type(self).__qualname__}",
            "state_names": list(self.state_names),
            "control_names": list(self.control_names),
            "dt": dt,
            "n_nodes": self.n_nodes,
            "params": self.params(),
        }  # effects are deliberately absent: data must not tell a model what it lacks

    # ---- dynamics ------------------------------------------------------------------------------------
    def dynamics(
        self,
        t: torch.Tensor,  # [] time
        x: torch.Tensor,  # [B, N, D] node states
        u: torch.Tensor | None = None,  # [B, N, C] controls
    ) -> torch.Tensor:
        """[B, N, D] the declared equations' dx/dt."""
        raise NotImplementedError

    def rhs(
        self,
        t: torch.Tensor,  # [] time
        x: torch.Tensor,  # [B, N, D] node states
        u: torch.Tensor | None = None,  # [B, N, C] controls
        history: Callable[[torch.Tensor], torch.Tensor] | None = None,  # state at an earlier time (delays)
    ) -> torch.Tensor:
        """[B, N, D] dx/dt: the declared dynamics plus every effect's term."""
        dx = self.dynamics(t, x, u)
        if self.effects:
            dx = dx + total(self.effects, t, x, self._context(x, history))
        return dx

    def _context(self, x: torch.Tensor, history=None) -> EffectContext:  # x: [B, N, D]
        key = (x.shape[0], x.device, x.dtype)
        if key not in self._contexts:
            self._contexts[key] = EffectContext.for_batch(self.edge_index, x)
        return EffectContext(self._contexts[key].graph, history)

    def energy(
        self,
        x: torch.Tensor,  # [..., N, D] states
        node_features: torch.Tensor | None = None,  # [..., N, F] or [N, F] static node features
    ) -> torch.Tensor | None:
        """[...] total energy where the system has one (None otherwise)."""
        return None

    def sample_initial_states(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """[n, N, D] float64 initial states drawn with `generator`."""
        raise NotImplementedError

    # ---- data ----------------------------------------------------------------------------------------
    def simulate(
        self,
        x0: torch.Tensor,  # [B, N, D] initial states
        t: torch.Tensor,  # [T] output times
        rtol: float = 1e-8,
        atol: float = 1e-10,
        method: str = "dopri5",
    ) -> Trajectories:
        """Integrate the true dynamics in float64 from `x0` and return the sampled trajectories."""
        x0 = x0.to(torch.float64)
        t = t.to(torch.float64)
        with torch.no_grad():  # ground truth: effect coefficients are constants here
            return self._simulate(x0, t, rtol, atol, method)

    def _simulate(self, x0, t, rtol, atol, method) -> Trajectories:
        delay = min_delay(self.effects)
        if delay > 0:  # a delayed term needs the history: fixed-step RK4 with interpolated history
            interval = float(t[1] - t[0]) if t.numel() > 1 else 0.0
            check_fixed_steps(self.name, delay_substeps(interval, 1e-3, delay), interval, self.dt)
            x = rk4_delay(lambda tt, xx, hist: self.rhs(tt, xx, history=hist), x0, t, step=1e-3, min_delay=delay)
        else:
            options = {"max_num_steps": GROUND_TRUTH_MAX_STEPS} if method in ADAPTIVE else None
            x = odeint(lambda tt, xx: self.rhs(tt, xx), x0, t, rtol=rtol, atol=atol, method=method, options=options)
            x = x.transpose(0, 1)
        return Trajectories(t=t, x=x.contiguous(), edge_index=self.edge_index, meta=self.meta(grid_step(t)))

    def generate(
        self,
        n: int,
        seed: int,
        dt: float | None = None,
        horizon: int | None = None,
        rtol: float = 1e-8,
        atol: float = 1e-10,
        burn_in: int = 0,
    ) -> Trajectories:
        """`n` trajectories of `horizon` steps of `dt` from initial states drawn with `seed`.

        `burn_in` steps are simulated first and discarded (e.g. to start on a chaotic attractor); the recorded
        times keep the clock running, so they start at burn_in·dt (time-dependent effects stay in phase).
        """
        dt = self.dt if dt is None else dt
        horizon = self.horizon if horizon is None else horizon
        if dt <= 0 or horizon < 1 or n < 1 or burn_in < 0:
            raise ConfigError(
                f"need dt > 0, horizon >= 1, n >= 1 and burn_in >= 0; got dt={dt}, horizon={horizon}, "
                f"n={n}, burn_in={burn_in}."
            )
        generator = torch.Generator().manual_seed(int(seed))
        x0 = self.sample_initial_states(n, generator)
        t = torch.arange(burn_in + horizon + 1, dtype=torch.float64) * dt
        out = self.simulate(x0, t, rtol=rtol, atol=atol)
        return out.time_slice(burn_in, burn_in + horizon + 1) if burn_in else out

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v}" for k, v in self.params().items() if not isinstance(v, list | dict))
        return f"{type(self).__name__}({self.name}: N={self.n_nodes}, D={self.state_dim}, {args})"
