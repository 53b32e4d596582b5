"""Couplings to neighbours: diffusive, and the phase couplings at harmonic k (see `mpsim.effects`)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch

from mpsim.effects.base import Effect, EffectContext
from mpsim.errors import ConfigError
from mpsim.graphs.batch import segment_sum, sum_aggregate


class DiffusiveCoupling(Effect):
    """c·Σ_j A_ij (s_j − s_i): an extra spring/diffusion along the graph's edges."""

    basis = ("sum_j (s_j - s_i)",)

    def features(self, t, x, ctx):
        s = x[..., self.source : self.source + 1]  # [B, N, 1]
        degree = sum_aggregate(torch.ones_like(s), ctx.graph)
        return sum_aggregate(s, ctx.graph) - degree * s

    def _formula(self, s):
        return f"{float(self.coef.detach()[0]):+.4g}·Σ_j({s}_j − {s}_i)"


def _phase_sum(fn, s: torch.Tensor, ctx: EffectContext, harmonic: int = 1) -> torch.Tensor:  # s: [B, N] sources
    """[B, N, 1] Σ_j A_ij fn(k·(s_j − s_i)) over each node's in-neighbours (one pass over the batched edges)."""
    b, n = s.shape
    flat = s.reshape(b * n)
    diff = flat[ctx.graph.src] - flat[ctx.graph.dst]  # [E'] sender − receiver
    term = fn(diff if harmonic == 1 else harmonic * diff)  # [E']
    return segment_sum(term, ctx.graph.dst, b * n).reshape(b, n, 1)


def _harmonic(value: Any, effect: str) -> int:
    """k of a coupling's harmonic sin/cos(k·(s_j − s_i)): an integer ≥ 1 (an integral float from a config too)."""
    whole = isinstance(value, int) or (isinstance(value, float) and value.is_integer())
    if isinstance(value, bool) or not whole or value < 1:
        raise ConfigError(
            f"{effect}.harmonic must be an integer >= 1 (k of sin/cos(k·(s_j − s_i)); 1 is the plain coupling); "
            f"got {value!r}."
        )
    return int(value)


class _PhaseCoupling(Effect):
    """c·Σ_j A_ij fn(k·(s_j − s_i)), the k-th harmonic of a coupling of phases (k = 1: the plain coupling).

    Args:
        harmonic: k ≥ 1 (fixed, not trained).
    """

    _symbol: str  # sin or cos

    def __init__(
        self,
        coef: float | Sequence[float] = 0.0,
        target: str | int = 0,
        source: str | int | None = None,
        learnable: bool = True,
        harmonic: int = 1,
    ) -> None:
        super().__init__(coef, target, source, learnable)
        self.harmonic = _harmonic(harmonic, type(self).__name__)
        if self.harmonic > 1:
            self.basis = (f"sum_j {self._symbol}({self.harmonic}(s_j - s_i))",)

    @property
    def name(self) -> str:
        return type(self).__name__ if self.harmonic == 1 else f"{type(self).__name__}(k={self.harmonic})"

    def features(self, t, x, ctx):
        return _phase_sum(self._wave, x[..., self.source], ctx, self.harmonic)

    def _wave(self, angle: torch.Tensor) -> torch.Tensor:  # angle: [E'] k·(s_j − s_i) per edge
        raise NotImplementedError

    def _formula(self, s):
        k = "" if self.harmonic == 1 else f"{self.harmonic}·"
        inside = f"{s}_j − {s}_i" if self.harmonic == 1 else f"({s}_j − {s}_i)"
        return f"{float(self.coef.detach()[0]):+.4g}·Σ_j {self._symbol}({k}{inside})"

    def config(self) -> dict[str, Any]:
        cfg = super().config()
        return cfg if self.harmonic == 1 else {**cfg, "harmonic": self.harmonic}  # k = 1: the key is left out

    def extra_repr(self) -> str:
        return super().extra_repr() + ("" if self.harmonic == 1 else f", harmonic={self.harmonic}")


class SineCoupling(_PhaseCoupling):
    """c·Σ_j A_ij sin(k·(s_j − s_i)): Kuramoto-type coupling of phases (`harmonic` k, default 1)."""

    basis = ("sum_j sin(s_j - s_i)",)
    _symbol = "sin"

    def _wave(self, angle):
        return torch.sin(angle)


class CosineCoupling(_PhaseCoupling):
    """c·Σ_j A_ij cos(k·(s_j − s_i)): with `SineCoupling`, a phase lag (frustration) α in Kuramoto coupling
    (`harmonic` k, default 1)."""

    basis = ("sum_j cos(s_j - s_i)",)
    _symbol = "cos"

    def _wave(self, angle):
        return torch.cos(angle)
