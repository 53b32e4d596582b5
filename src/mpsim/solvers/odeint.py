"""`ODESolver`: how a model's vector field is integrated, behind one small object (torchdiffeq inside).

mpsim is batch-first; torchdiffeq is time-first. This is the only place that converts.

torchdiffeq's `odeint` writes each output into a preallocated [T, ...] tensor. Autograd then clones the whole
[T, ...] gradient once per write (the backward of an in-place slice assignment), an O(T²) copy that took 38 % of a
gene 8×8 MP-NODE training step from fresh weights (50 outputs, few dopri5 steps per output). `_odeint_stacked`
runs the same torchdiffeq solver object step by step and stacks the outputs once: the same steps and the same
numbers (tested against `odeint` for every method), a cheaper backward. It uses torchdiffeq's solver internals;
if they are not there, `odeint` itself is used.

dopri5, the default and the paper's method, runs by default on mpsim's own Dormand–Prince (`solvers/dopri5.py`):
torchdiffeq's steps and values to rounding, with much less bookkeeping per step (MP-NODE epochs 1.1–2× faster);
`implementation="torchdiffeq"` runs torchdiffeq's.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import nn
from torchdiffeq import odeint, odeint_adjoint

try:  # torchdiffeq 0.2's own solver objects, driven step by step by `_odeint_stacked`
    from torchdiffeq._impl.misc import _check_inputs
    from torchdiffeq._impl.odeint import SOLVERS
    from torchdiffeq._impl.solvers import AdaptiveStepsizeODESolver, FixedGridODESolver
except ImportError:  # pragma: no cover - another layout: plain odeint
    SOLVERS = None

from mpsim.errors import ConfigError, DivergenceError
from mpsim.solvers.dopri5 import StepFailure, dopri5

ADAPTIVE = ("dopri5", "dopri8", "bosh3", "fehlberg2", "adaptive_heun")
IMPLEMENTATIONS = ("mpsim", "torchdiffeq")
FIXED = ("euler", "midpoint", "heun2", "heun3", "rk4", "explicit_adams", "implicit_adams")


class ODESolver:
    """Integrate `dy/dt = func(t, y)` and return the states at the requested times, batch first.

    Args:
        method: a torchdiffeq method (adaptive: dopri5, dopri8, bosh3, ...; fixed-step: rk4, euler, ...).
        rtol, atol: tolerances of adaptive methods.
        step_size: step of fixed-step methods (None: one step per output interval).
        adjoint: backpropagate with the continuous adjoint (less memory, usually slower).
        max_num_steps: adaptive steps allowed per output interval before the rollout counts as diverged
            (a learned field that became stiff would otherwise stall training); fixed-step methods refuse a
            `step_size` that would need more steps than this per output interval.
        stacked: collect the outputs in a list and stack them (the default: same numbers, cheaper backward);
            false runs torchdiffeq's `odeint` as is, to measure the difference (`mpsim bench bench=mpnode`).
        implementation: who integrates dopri5 (stacked, without the adjoint): "mpsim" (`solvers/dopri5.py`: the
            same steps, much less overhead per step, step sizes not differentiated) or "torchdiffeq".
    """

    def __init__(
        self,
        method: str = "dopri5",
        rtol: float = 1e-4,
        atol: float = 1e-4,
        step_size: float | None = None,
        adjoint: bool = False,
        max_num_steps: int = 10_000,
        stacked: bool = True,
        implementation: str = "mpsim",
    ) -> None:
        if method not in ADAPTIVE + FIXED:
            raise ConfigError(
                f"solver.method={method!r} is not a torchdiffeq method; choose one of {ADAPTIVE + FIXED}."
            )
        if method in ADAPTIVE and (rtol <= 0 or atol <= 0):
            raise ConfigError(f"solver.rtol and solver.atol must be > 0; got {rtol}, {atol}.")
        if step_size is not None and step_size <= 0:
            raise ConfigError(f"solver.step_size must be > 0 or null; got {step_size}.")
        if max_num_steps < 1:
            raise ConfigError(f"solver.max_num_steps must be >= 1; got {max_num_steps}.")
        self.method, self.rtol, self.atol = method, float(rtol), float(atol)
        self.step_size, self.adjoint, self.max_num_steps = step_size, bool(adjoint), int(max_num_steps)
        self.stacked = bool(stacked)
        if implementation not in IMPLEMENTATIONS:
            raise ConfigError(
                f"solver.implementation={implementation!r} is not known; choose one of {IMPLEMENTATIONS}."
            )
        self.implementation = implementation

    def _check_fixed_steps(self, interval: float) -> None:
        """Refuse a fixed step so small that one output interval would take more than max_num_steps steps
        (torchdiffeq lays the whole grid out at once: solver.step_size=1e-12 asked for 20 TB)."""
        assert self.step_size is not None
        steps = math.ceil(interval / self.step_size - 1e-9)
        if steps > self.max_num_steps:
            raise ConfigError(
                f"solver.step_size={self.step_size:g} needs {steps:.3g} {self.method} steps per sampling interval of "
                f"{interval:.4g} (solver.max_num_steps={self.max_num_steps}). Use a larger solver.step_size, e.g. "
                f"{interval / 4:.3g}, or null for one step per interval."
            )

    @property
    def restarts(self) -> bool:
        """Whether `__call__(..., restart=True)` is available: mpsim's own dopri5 (stacked, without the adjoint)."""
        return self.method == "dopri5" and self.implementation == "mpsim" and self.stacked and not self.adjoint

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
        restart: bool = False,
    ) -> torch.Tensor:
        """[B, T, ...] the solution at each time in `t`.

        `restart=True` (only where `restarts`): the field jumps at every output time (a zero-order-hold input);
        no step straddles one and the field is evaluated afresh on each (`mpsim.solvers.dopri5`).

        Raises:
            DivergenceError: the state became NaN/inf or the adaptive step size underflowed.
        """
        if restart and not self.restarts:
            raise ValueError(f"{self!r} cannot restart at output times; solve one interval at a time instead.")
        t = t.to(device=y0.device, dtype=y0.dtype)
        if self.step_size is not None and self.method in FIXED and t.numel() > 1:
            self._check_fixed_steps(float((t[1:] - t[:-1]).abs().max()))
        own = self.method == "dopri5" and self.implementation == "mpsim" and self.stacked and not self.adjoint
        try:
            if own:
                ys = dopri5(func, y0, t, self.rtol, self.atol, self.max_num_steps, restart)
            else:
                stacked = self.stacked and SOLVERS is not None
                solve = odeint_adjoint if self.adjoint else _odeint_stacked if stacked else odeint
                ys = solve(func, y0, t, rtol=self.rtol, atol=self.atol, method=self.method, options=self.options)
        except (AssertionError, StepFailure) as err:  # torchdiffeq reports numerical failure with assert
            text = str(err).split(":")[0]
            raise DivergenceError(
                f"ODE solver failed ({text}): the vector field became stiff or blew up. Try a smaller learning "
                "rate, solver=rk4, or a tighter trainer.clip_norm."
            ) from None
        return ys.movedim(0, 1)

    def __repr__(self) -> str:
        extra = f"rtol={self.rtol:g}, atol={self.atol:g}" if self.method in ADAPTIVE else f"step={self.step_size}"
        return f"ODESolver({self.method}, {extra}{', adjoint' if self.adjoint else ''})"


def _odeint_stacked(
    func: nn.Module,  # vector field: forward(t [], y [B, ...]) -> [B, ...]
    y0: torch.Tensor,  # [B, ...] initial state
    t: torch.Tensor,  # [T] output times
    *,
    rtol: float,
    atol: float,
    method: str,
    options: dict[str, Any],
) -> torch.Tensor:
    """[T, B, ...] what `torchdiffeq.odeint` returns, its outputs collected in a list and stacked once (see the
    module docstring): the same solver object advanced the same way, so the same steps and values."""
    _, func, y0, t, rtol, atol, method, options, _, _ = _check_inputs(
        func, y0, t, rtol, atol, method, options, None, SOLVERS
    )
    solver = SOLVERS[method](func=func, y0=y0, rtol=rtol, atol=atol, **options)
    if isinstance(solver, AdaptiveStepsizeODESolver):
        ts = t.to(solver.dtype)
        solver._before_integrate(ts)
        return torch.stack([solver.y0, *(solver._advance(ts[i]) for i in range(1, len(ts)))])
    if not isinstance(solver, FixedGridODESolver) or solver.interp != "linear":
        return solver.integrate(t)
    grid = solver.grid_constructor(solver.func, solver.y0, t)  # [K] the solver's own steps
    out, j, y = [solver.y0], 1, solver.y0
    for t0, t1 in zip(grid[:-1], grid[1:], strict=True):
        dt = t1 - t0
        solver.func.callback_step(t0, y, dt)
        dy, _ = solver._step_func(solver.func, t0, dt, t1, y)
        y1 = y + dy
        while j < len(t) and t1 >= t[j]:  # every output time inside this step, interpolated linearly
            out.append(solver._linear_interp(t0, t1, y, y1, t[j]))
            j += 1
        y = y1
    if len(out) != len(t):  # pragma: no cover - the grid always ends at t[-1]
        raise RuntimeError(f"fixed-grid {method}: {len(out)} outputs for {len(t)} times.")
    return torch.stack(out)
