"""`ODESolver`: how a model's vector field is integrated, behind one small object (torchdiffeq inside).

mpsim is batch-first; torchdiffeq is time-first. This is the only place that converts.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn
from torchdiffeq import odeint, odeint_adjoint

from mpsim.errors import ConfigError, DivergenceError

ADAPTIVE = ("dopri5", "dopri8", "bosh3", "fehlberg2", "adaptive_heun")
FIXED = ("euler", "midpoint", "heun2", "heun3", "rk4", "explicit_adams", "implicit_adams")


class ODESolver:
    """Integrate `dy/dt = func(t, y)` and return the states at the requested times, batch first.

    Args:
        method: a torchdiffeq method (adaptive: dopri5, dopri8, bosh3, ...; fixed-step: rk4, euler, ...).
        rtol, atol: tolerances of adaptive methods.
        step_size: step of fixed-step methods (None: one step per output interval).
        adjoint: backpropagate with the continuous adjoint (less memory, usually slower).
        max_num_steps: adaptive steps allowed per output interval before the rollout counts as diverged
            (a learned field that became stiff would otherwise stall training).
    """

    def __init__(
        self,
        method: str = "dopri5",
        rtol: float = 1e-4,
        atol: float = 1e-4,
        step_size: float | None = None,
        adjoint: bool = False,
        max_num_steps: int = 10_000,
    ) -> None:
        if method not in ADAPTIVE + FIXED:
            raise ConfigError(
                f"solver.method={method!r} is not a torchdiffeq method; choose one of {ADAPTIVE + FIXED}."
            )
        if method in ADAPTIVE and (rtol <= 0 or atol <= 0):
            raise ConfigError(f"solver.rtol and solver.atol must be > 0; got {rtol}, {atol}.")
        if step_size is not None and step_size <= 0:
            raise ConfigError(f"solver.step_size must be > 0 or null; got {step_size}.")
        self.method, self.rtol, self.atol = method, float(rtol), float(atol)
        self.step_size, self.adjoint, self.max_num_steps = step_size, bool(adjoint), int(max_num_steps)

    @property
    def options(self) -> dict[str, Any]:
        if self.method in ADAPTIVE:
            return {"max_num_steps": self.max_num_steps}
        return {} if self.step_size is None else {"step_size": self.step_size}

    def __call__(
        self,
        func: nn.Module,  # vector field: forward(t [], y [B, ...]) -> [B, ...]
        y0: torch.Tensor,  # [B, ...] initial state
        t: torch.Tensor,  # [T] output times
    ) -> torch.Tensor:
        """[B, T, ...] the solution at each time in `t`.

        Raises:
            DivergenceError: the state became NaN/inf or the adaptive step size underflowed.
        """
        t = t.to(device=y0.device, dtype=y0.dtype)
        solve = odeint_adjoint if self.adjoint else odeint
        try:
            ys = solve(func, y0, t, rtol=self.rtol, atol=self.atol, method=self.method, options=self.options)
        except AssertionError as err:  # torchdiffeq reports numerical failure with assert
            text = str(err).split(":")[0]
            raise DivergenceError(
                f"ODE solver failed ({text}): the vector field became stiff or blew up. Try a smaller learning "
                "rate, solver=rk4, or a tighter trainer.clip_norm."
            ) from None
        return ys.movedim(0, 1)

    def __repr__(self) -> str:
        extra = f"rtol={self.rtol:g}, atol={self.atol:g}" if self.method in ADAPTIVE else f"step={self.step_size}"
        return f"ODESolver({self.method}, {extra}{', adjoint' if self.adjoint else ''})"
