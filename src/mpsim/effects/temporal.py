"""The effects that read time or the history: a drive, a delayed feedback, a drifting parameter (and the delays a
model's integrator must know). See the package's docstring (`mpsim.effects`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import nn

from mpsim.effects.base import Effect
from mpsim.errors import ConfigError


class PeriodicForcing(Effect):
    """A·sin(ω t + φ): an external periodic drive with learnable amplitude, angular frequency and phase.

    With `random_phase`, trajectory b of a batch is driven by A·sin(ω t + φ + φ_b), φ_b ~ U(0, 2π) drawn for
    b = 0..B−1 from `torch.Generator().manual_seed(phase_seed)`: recordings that start at arbitrary times of
    the same drive (A and ω shared). Meant for generating data; the B phases depend only on B and the seed.

    Args:
        amplitude, omega, phase: A, ω (rad per unit time), φ (rad).
        target: the driven state variable.
        learnable: whether A, ω and φ are trained.
        random_phase: give every trajectory of a batch its own extra phase φ_b.
        phase_seed: the seed of the φ_b draws.
    """

    basis = ("sin(wt)", "cos(wt)")
    uses_time = True

    def __init__(
        self,
        amplitude: float = 0.0,
        omega: float = 1.0,
        phase: float = 0.0,
        target: str | int = 0,
        source: str | int | None = None,
        learnable: bool = True,
        random_phase: bool = False,
        phase_seed: int = 0,
    ) -> None:
        a, b = amplitude * math.cos(phase), amplitude * math.sin(phase)  # A sin(ωt+φ) = a sin ωt + b cos ωt
        super().__init__([a, b], target, source, learnable)
        if omega <= 0:
            raise ConfigError(f"PeriodicForcing.omega must be > 0; got {omega}.")
        if not isinstance(random_phase, bool):
            raise ConfigError(f"PeriodicForcing.random_phase must be true or false; got {random_phase!r}.")
        if isinstance(phase_seed, bool) or not isinstance(phase_seed, int) or phase_seed < 0:
            raise ConfigError(f"PeriodicForcing.phase_seed must be an integer >= 0; got {phase_seed!r}.")
        self.log_omega = nn.Parameter(torch.tensor(math.log(omega), dtype=torch.float64), requires_grad=learnable)
        self.random_phase, self.phase_seed = random_phase, int(phase_seed)
        self._phases: dict[int, torch.Tensor] = {}

    @property
    def per_record(self) -> bool:  # type: ignore[override]
        return self.random_phase  # φ_b follows the record's place in the batch

    @property
    def omega(self) -> float:
        return float(self.log_omega.detach().exp())

    def amplitude_phase(self) -> tuple[float, float]:
        a, b = (float(c) for c in self.coef.detach())
        return math.hypot(a, b), math.atan2(b, a)

    def trajectory_phases(self, n: int) -> torch.Tensor:
        """[n] float64 φ_b of trajectories 0..n−1 (zeros without `random_phase`)."""
        if not self.random_phase:
            return torch.zeros(n, dtype=torch.float64)
        if n not in self._phases:
            gen = torch.Generator().manual_seed(self.phase_seed)
            self._phases[n] = 2 * math.pi * torch.rand(n, generator=gen, dtype=torch.float64)
        return self._phases[n]

    def features(self, t, x, ctx):
        # t: [] or broadcastable to [B, N] (per-sample times when the residual loop builds its library)
        phase = self.log_omega.exp().to(x) * torch.broadcast_to(torch.as_tensor(t).to(x), x.shape[:-1])
        if self.random_phase:
            phase = phase + self.trajectory_phases(x.shape[0]).to(x)[:, None]
        return torch.stack([torch.sin(phase), torch.cos(phase)], dim=-1)

    def _formula(self, s):
        amp, ph = self.amplitude_phase()
        return f"{amp:.4g}·sin({self.omega:.4g}·t {ph:+.3f}{' + φ_b' if self.random_phase else ''})"

    def config(self) -> dict[str, Any]:
        amp, ph = self.amplitude_phase()
        cfg = super().config()
        del cfg["coef"], cfg["source"]
        cfg = {**cfg, "amplitude": amp, "omega": self.omega, "phase": ph}
        if self.random_phase:
            cfg.update(random_phase=True, phase_seed=self.phase_seed)
        return cfg


class DelayedFeedback(Effect):
    """c·s(t − τ): delayed self-feedback (needs the state history: a fixed-step delay integrator).

    τ is a number, not a multiple of the sampling step: the history is interpolated linearly between stored
    states, and τ is a parameter (log τ, so it stays positive) that a fit moves with c when `learnable`.

    Args:
        coef: c.
        delay: τ > 0 in the data's time units.
        target: the state variable whose derivative receives the term.
        source: the delayed state variable (default: the target).
        learnable: whether c and τ are trained.
    """

    basis = ("s(t-tau)",)

    def __init__(
        self,
        coef: float = 0.0,
        delay: float = 0.1,
        target: str | int = 0,
        source: str | int | None = None,
        learnable: bool = True,
    ) -> None:
        super().__init__(coef, target, source, learnable)
        if not delay > 0 or math.isinf(delay):
            raise ConfigError(f"DelayedFeedback.delay must be a finite number > 0; got {delay}.")
        self.log_delay = nn.Parameter(torch.tensor(math.log(delay), dtype=torch.float64), requires_grad=learnable)

    def tau(self) -> torch.Tensor:
        """[] τ as a tensor (its gradient reaches log τ), kept within e^±30 (a fit's trial step never makes it 0)."""
        return self.log_delay.clamp(-30.0, 30.0).exp()

    @property
    def delay(self) -> float:
        """τ, the current delay."""
        return float(self.tau().detach())

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # a checkpoint from before τ was a parameter: τ stays the configured one
        state_dict.setdefault(prefix + "log_delay", self.log_delay.detach().clone())
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def features(self, t, x, ctx):
        if ctx.history is None:
            raise ConfigError(
                "DelayedFeedback needs the state history: integrate with a delay-aware solver "
                "(systems and models switch to one automatically when a delay effect is present)."
            )
        past = ctx.history(torch.as_tensor(t, dtype=x.dtype) - self.tau().to(x))
        return past[..., self.source : self.source + 1]

    def _formula(self, s):
        return f"{float(self.coef.detach()[0]):+.4g}·{s}(t − {self.delay:.4g})"

    def config(self) -> dict[str, Any]:
        return {**super().config(), "delay": self.delay}


class ParameterDrift(Effect):
    """p(t) = p·(1 + s·t): the nominal parameter `param` of a white-box model drifts linearly in time.

    Not a term of one state variable: it changes the model's own parameter wherever the equations read it, so
    only a model that reads its parameters applies it (`model=equations`: `EquationsModel`); every other model
    or system refuses it. `t` is the data's own time (the recordings' time axis, starting at their t[0]): the
    drift is relative to t = 0 of the data, where p(0) = p. The coefficient is the relative rate s (per unit
    time); `target` is kept only as the row the residual loop found it on (the drift acts on every row).

    Args:
        param: name of the drifting parameter (a scalar of the model's spec).
        rate: s, the relative change of p per unit time.
    """

    basis = ("t*p*df/dp",)
    uses_time = True
    #: applied by the model to its own parameters, not added to dx/dt (`EquationsModel`)
    acts_on_parameters = True

    def __init__(
        self,
        param: str = "p",
        rate: float = 0.0,
        target: str | int = 0,
        source: str | int | None = None,
        learnable: bool = True,
    ) -> None:
        super().__init__(rate, target, source, learnable)
        self.param = str(param)

    @property
    def rate(self) -> float:
        return float(self.coef.detach()[0])

    def factor(self, t: torch.Tensor) -> torch.Tensor:  # t: [] or [M, 1] absolute time of the data
        """1 + s·t, in t's shape."""
        return 1.0 + self.coef[0].to(t) * t

    def features(self, t, x, ctx):
        raise ConfigError(
            f"ParameterDrift({self.param}) changes a model's own parameter: only model=equations applies it "
            "(it is no term a system or another model can add to dx/dt)."
        )

    def forward(self, t, x, ctx):
        return self.features(t, x, ctx)

    def describe(self) -> str:
        return f"{self.param} drifts: {self.param}·(1 + s·t), s = {self.rate:.4g}"

    def config(self) -> dict[str, Any]:
        cfg = super().config()
        del cfg["source"], cfg["coef"]
        return {**cfg, "param": self.param, "rate": self.rate}

    def extra_repr(self) -> str:
        return f"param={self.param}, rate={self.rate:.6g}"


def min_delay(effects: Sequence[Effect] | nn.ModuleList) -> float:
    """The smallest delay among `effects` (0 if there is no delayed term)."""
    return min((e.delay for e in effects if isinstance(e, DelayedFeedback)), default=0.0)


def max_delay(effects: Sequence[Effect] | nn.ModuleList) -> float:
    """The longest delay among `effects` (0 if there is no delayed term): how far back a rollout reads."""
    return max((e.delay for e in effects if isinstance(e, DelayedFeedback)), default=0.0)
