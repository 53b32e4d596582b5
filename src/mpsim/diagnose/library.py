"""The candidate library: named effects whose basis functions a residual is regressed on.

A candidate is an effect class with a source state variable (and, for forcing and delays, its frequency or
delay). Its basis functions are evaluated in the same time-stepping as the one-step residual: averaged over
the step with the trapezoid rule, φ̄_k = ½(φ(t_k, x_k) + φ(t_{k+1}, x_{k+1})), on the observed states, so a
term c·φ integrated over one step contributes c·φ̄_k to the residual up to O(Δ²).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import torch

from mpsim import effects as fx
from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.params import DEFAULT_KINDS as _KINDS
from mpsim.effects import EffectContext

#: effect kinds of the default library, by class name (one list: `mpsim.diagnose.params`)
DEFAULT_KINDS = tuple(_KINDS)
NEEDS_GRAPH = ("DiffusiveCoupling", "SineCoupling", "CosineCoupling")
#: dry friction's smoothing scale, as a share of its source's standard deviation in the data
DRY_SCALE = 0.01


@dataclass
class Candidate:
    """One candidate effect: its class, source variable, fixed parameters and basis columns.

    Attributes:
        kind: effect class name in `mpsim.effects`.
        source: source state index (None for terms without a source: bias, forcing).
        params: fixed constructor arguments (omega of a forcing, delay of a feedback).
        features: [B, T−1, N, K] step-averaged basis functions.
    """

    kind: str
    source: int | None
    params: dict[str, Any] = field(default_factory=dict)
    features: torch.Tensor | None = None

    def label(self, state_names: list[str], target: int | None = None) -> str:
        src = "" if self.source is None else state_names[self.source]
        extra = ""
        if "omega" in self.params:
            extra = f"ω={self.params['omega']:.4g}"
        if "delay" in self.params:
            extra = f"τ={self.params['delay']:.4g}"
        inside = ", ".join(p for p in (src, extra) if p)
        name = f"{self.kind}({inside})" if inside else self.kind
        return name if target is None else f"d{state_names[target]}/dt: {name}"

    def effect_config(self, coef: list[float], target: int, state_names: list[str]) -> dict[str, Any]:
        """The Hydra config of this effect with fitted coefficients (for `model.effects`)."""
        cfg: dict[str, Any] = {"_target_": f"mpsim.effects.{self.kind}", "target": state_names[target]}
        if self.kind == "PeriodicForcing":
            a, b = coef
            cfg.update(amplitude=math.hypot(a, b), phase=math.atan2(b, a), omega=self.params["omega"])
            return cfg
        cfg["coef"] = coef[0]
        if self.source is not None:
            cfg["source"] = state_names[self.source]
        for key in ("delay", "scale"):
            if key in self.params:
                cfg[key] = self.params[key]
        return cfg

    def make_effect(self, coef: list[float], target: int, state_names: list[str]) -> fx.Effect:
        """The effect object with fitted coefficients, bound to the data's state names."""
        cfg = self.effect_config(coef, target, state_names)
        effect = getattr(fx, self.kind)(**{k: v for k, v in cfg.items() if k != "_target_"})
        effect.bind(state_names)
        return effect


def _step_average(values: torch.Tensor) -> torch.Tensor:  # values: [B, T, N, K]
    """[B, T−1, N, K] trapezoid average over each step."""
    return 0.5 * (values[:, 1:] + values[:, :-1])


def evaluate_effect(effect: fx.Effect, data: Trajectories) -> torch.Tensor:
    """[B, T, N, K] an effect's basis functions at every observed state and time."""
    b, n_t, n, d = data.x.shape
    flat = data.x.double().reshape(b * n_t, n, d)
    t = data.t.double()[None, :].expand(b, n_t).reshape(b * n_t, 1)
    ei = data.edge_index if data.shared_graph else data.edge_index.repeat_interleave(n_t, dim=0)
    ctx = EffectContext.for_batch(ei, flat)
    return effect.features(t, flat, ctx).reshape(b, n_t, n, -1)


def delayed(x: torch.Tensor, m: int) -> torch.Tensor:  # x: [B, T, N, D]
    """[B, T, N, D] x shifted by m steps (constant initial history before t0, as in the delay integrator)."""
    if m <= 0:
        return x
    head = x[:, :1].expand(-1, m, -1, -1)
    return torch.cat([head, x[:, :-m]], dim=1)


@torch.no_grad()
def build_library(
    data: Trajectories,
    omegas: dict[int, float] | None = None,
    delays: list[float] | None = None,
    kinds: tuple[str, ...] = DEFAULT_KINDS,
) -> list[Candidate]:
    """Evaluate every candidate's basis on `data`.

    Args:
        data: the observed trajectories (uniform time grid for delays).
        omegas: {target index: angular frequency} of forcing candidates (from the residual periodogram);
            one forcing candidate per distinct frequency.
        delays: delays of the feedback candidates (multiples of the sampling step).
        kinds: effect class names to include.
    """
    d = data.state_dim
    has_edges = data.edge_index.numel() > 0 and bool((data.edge_index >= 0).any())
    out: list[Candidate] = []
    for kind in kinds:
        if kind in NEEDS_GRAPH and not has_edges:
            continue
        cls = getattr(fx, kind)
        if kind == "Bias":
            effect = cls(0.0, target=0).bind(data.state_names)
            out.append(Candidate(kind, None, {}, _step_average(evaluate_effect(effect, data))))
        elif kind == "PeriodicForcing":
            for omega in sorted(set((omegas or {}).values())):
                effect = cls(0.0, omega=omega, target=0).bind(data.state_names)
                out.append(Candidate(kind, None, {"omega": omega}, _step_average(evaluate_effect(effect, data))))
        elif kind == "DryFriction":
            spread = data.x.double().reshape(-1, d).std(0)
            for s in range(d):
                scale = max(DRY_SCALE * float(spread[s]), 1e-9)
                effect = cls(0.0, target=0, source=s, scale=scale).bind(data.state_names)
                out.append(Candidate(kind, s, {"scale": scale}, _step_average(evaluate_effect(effect, data))))
        elif kind == "DelayedFeedback":
            dt = float(data.t[1] - data.t[0])
            for tau in delays or []:
                m = int(round(tau / dt))
                if m < 1 or m >= data.n_times - 1:
                    continue
                past = delayed(data.x.double(), m)
                for s in range(d):
                    out.append(Candidate(kind, s, {"delay": m * dt}, _step_average(past[..., s : s + 1])))
        else:
            for s in range(d):
                effect = cls(0.0, target=0, source=s).bind(data.state_names)
                out.append(Candidate(kind, s, {}, _step_average(evaluate_effect(effect, data))))
    return out


def dominant_frequency(
    r: torch.Tensor,  # [B, T−1, N] residual of one state variable
    t_mid: torch.Tensor,  # [T−1] step midpoints
    pad: int = 16,
) -> tuple[float, torch.Tensor, torch.Tensor]:
    """(angular frequency of the residual's periodogram peak, [F] frequencies (rad), [F] power).

    The residual is averaged over trajectories and nodes first: an external drive keeps its phase across
    trajectories that share a clock, while state-dependent model error does not and averages out.
    """
    signal = r.double().mean(dim=(0, 2))
    signal = signal - signal.mean()
    n = signal.numel()
    dt = float((t_mid[-1] - t_mid[0]) / max(n - 1, 1))
    window = torch.hann_window(n, periodic=False, dtype=torch.float64)
    spec = torch.fft.rfft(signal * window, n=pad * n)
    power = spec.abs().pow(2)
    freqs = 2 * math.pi * torch.fft.rfftfreq(pad * n, d=dt, dtype=torch.float64)
    lowest = 2 * pad  # skip the window's main lobe around zero frequency (trends, not oscillations)
    k = lowest + int(torch.argmax(power[lowest:]))
    return float(freqs[k]), freqs, power


def refine_frequency(
    y: torch.Tensor,  # [n] residual samples of one state variable
    times: torch.Tensor,  # [n] their times
    omega0: float,
    span: float,
    others: torch.Tensor | None = None,  # [n, p] other regressors kept in the fit
) -> float:
    """The ω near `omega0` (within ±span) that maximises the fit of y on [sin ωt, cos ωt] (+ others):
    a grid then golden-section search of the residual sum of squares."""

    def rss(omega: float) -> float:
        cols = [torch.sin(omega * times), torch.cos(omega * times), torch.ones_like(times)]
        x = torch.stack(cols, dim=1)
        if others is not None:
            x = torch.cat([x, others], dim=1)
        sol = torch.linalg.lstsq(x, y[:, None]).solution
        return float((y[:, None] - x @ sol).pow(2).sum())

    grid = torch.linspace(max(omega0 - span, 1e-6), omega0 + span, 41, dtype=torch.float64)
    values = [rss(float(w)) for w in grid]  # 41 small least-squares fits
    k = int(torch.argmin(torch.tensor(values)))
    lo, hi = float(grid[max(k - 1, 0)]), float(grid[min(k + 1, len(grid) - 1)])
    g = (math.sqrt(5) - 1) / 2
    a, b = hi - g * (hi - lo), lo + g * (hi - lo)
    fa, fb = rss(a), rss(b)
    for _ in range(40):
        if fa < fb:
            hi, b, fb = b, a, fa
            a = hi - g * (hi - lo)
            fa = rss(a)
        else:
            lo, a, fa = a, b, fb
            b = lo + g * (hi - lo)
            fb = rss(b)
    return 0.5 * (lo + hi)
