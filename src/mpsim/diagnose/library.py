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
from mpsim.diagnose.noise import resolution
from mpsim.diagnose.params import DEFAULT_KINDS as _KINDS
from mpsim.diagnose.params import HARMONICS, complexity
from mpsim.effects import EffectContext

#: effect kinds of the default library, by class name (one list: `mpsim.diagnose.params`)
DEFAULT_KINDS = tuple(_KINDS)
#: kinds whose columns come from the model, not the data alone (`nuisance.drift_candidates`,
#: `nuisance.input_candidates`)
MODEL_KINDS = ("ParameterDrift", "InputGain", "DeadZone", "InputSaturation")
NEEDS_GRAPH = ("DiffusiveCoupling", "SineCoupling", "CosineCoupling")
#: couplings of phases offered at every harmonic k of `params.HARMONICS`: sin/cos(k(θ_j − θ_i))
HARMONIC_KINDS = ("SineCoupling", "CosineCoupling")
#: dry friction's sign(v) is smoothed over the data's velocity resolution (`noise.resolution`: noise level or
#: quantisation step), but never over less than this share of the velocity's spread: a sharper tanh makes the
#: model's adaptive integrator stiff and the multiple-shooting fit rough (measured on scorecard case d, clean data:
#: ε = 0.12 % of the spread gave μ 6.5 % low, ε = 1 % gave 0.1 %)
DRY_MIN_SCALE = 0.01
#: dry friction reverses with the sign of its source: a source with fewer than this share of its samples beyond −ε
#: (or beyond +ε, whichever side is the smaller) never shows the reversal, and −c·tanh(s/ε) is a constant (or a
#: one-sided saturation) there, not friction (issue 61: a constant term on an always-positive position was named
#: "dry friction" of that position)
DRY_MIN_SIGN_SHARE = 0.01
#: below this spread (standard deviation) of tanh(s/ε) over the samples, −c·tanh(s/ε) is a constant on the data
DRY_CONSTANT_SPREAD = 0.01


@dataclass
class Candidate:
    """One candidate effect: its class, source variable, fixed parameters and basis columns.

    Attributes:
        kind: effect class name in `mpsim.effects`.
        source: source state index (None for terms without a source: bias, forcing).
        params: fixed constructor arguments (omega of a forcing, delay of a feedback, harmonic k > 1 of a
            coupling: absent for k = 1).
        features: [B, T−1, N, K] step-averaged basis functions ([B, T−1, N, D, K] with `per_row`).
        per_row: the basis differs between state rows (a parameter drift's t·p·∂f_d/∂p): `row(d)` is row d's.
        nodes: the nodes a per-node variant acts on (`per_node`: one column, one coefficient per listed node;
            None: one coefficient shared by all nodes).
    """

    kind: str
    source: int | None
    params: dict[str, Any] = field(default_factory=dict)
    features: torch.Tensor | None = None
    per_row: bool = False
    nodes: tuple[int, ...] | None = None

    @property
    def harmonic(self) -> int:
        """k of a coupling's harmonic sin/cos(k(θ_j − θ_i)) (1 for every other candidate)."""
        return int(self.params.get("harmonic", 1))

    @property
    def family(self) -> tuple[str, int]:
        """What counts as one kind where the loop keeps one candidate per kind: (kind, harmonic)."""
        return self.kind, self.harmonic

    @property
    def complexity(self) -> float:
        """The kind's complexity (`params.complexity`: higher harmonics are more complex)."""
        return complexity(self.kind, self.harmonic)

    @property
    def basis(self) -> torch.Tensor:
        """[B, T−1, N, K] the evaluated basis (`build_library` fills `features`)."""
        if self.features is None:
            raise ValueError(f"candidate {self.kind} has no evaluated basis: build it with build_library")
        return self.features

    def row(self, d: int) -> torch.Tensor:
        """[B, T−1, N, K] the basis on state row d (the same on every row but for a `per_row` candidate)."""
        return self.basis[..., d, :] if self.per_row else self.basis

    def label(self, state_names: list[str], target: int | None = None) -> str:
        src = "" if self.source is None else state_names[self.source]
        extra = str(self.params.get("param", ""))
        if "omega" in self.params:
            extra = f"ω={self.params['omega']:.4g}" + (", a phase per recording" if self.params.get("phased") else "")
        if "delay" in self.params:
            extra = f"τ={self.params['delay']:.4g}"
        if self.kind == "InputGain":
            extra = f"{self.params['input']}, a gain per recording"
        for key in ("width", "limit"):  # a dead zone's, a saturation's threshold
            if key in self.params:
                extra = f"{self.params['input']}, {key}={self.params[key]:.4g}"
        if self.harmonic > 1:
            extra = f"k={self.harmonic}"
        if self.nodes is not None:
            extra = node_text(self.nodes)
        inside = ", ".join(p for p in (src, extra) if p)
        name = f"{self.kind}({inside})" if inside else self.kind
        return name if target is None else f"d{state_names[target]}/dt: {name}"

    def effect_config(self, coef: list[float], target: int, state_names: list[str]) -> dict[str, Any]:
        """The Hydra config of this effect with fitted coefficients (for `model.effects`)."""
        cfg: dict[str, Any] = {"_target_": f"mpsim.effects.{self.kind}", "target": state_names[target]}
        if self.kind == "InputGain":  # (1 + c_b)·u: one gain per recording
            return {**cfg, "input": self.params["input"], "gains": [1.0 + float(c) for c in coef]}
        if self.kind in ("DeadZone", "InputSaturation"):  # the threshold of the screen's grid; the fit moves it
            key = "width" if self.kind == "DeadZone" else "limit"
            return {**cfg, "input": self.params["input"], key: self.params[key]}
        if self.kind == "ParameterDrift":  # p·(1 + s·t): the rate s of the named parameter
            return {**cfg, "param": self.params["param"], "rate": coef[0]}
        if self.params.get("phased"):  # one (a, b) pair per recording: a shared amplitude, a phase each
            pairs = torch.tensor(coef, dtype=torch.float64).reshape(-1, 2)
            return {
                "_target_": "mpsim.diagnose.library.PhasedDrive",
                "target": state_names[target],
                "amplitude": float(pairs.norm(dim=1).mean()),
                "omega": self.params["omega"],
                "phases": torch.atan2(pairs[:, 1], pairs[:, 0]).tolist(),
            }
        if self.kind == "PeriodicForcing":
            a, b = coef
            cfg.update(amplitude=math.hypot(a, b), phase=math.atan2(b, a), omega=self.params["omega"])
            return cfg
        cfg["coef"] = coef[0] if self.nodes is None else list(coef)
        if self.nodes is not None:
            cfg["nodes"] = list(self.nodes)
        if self.source is not None:
            cfg["source"] = state_names[self.source]
        for key in ("delay", "scale", "harmonic"):
            if key in self.params:
                cfg[key] = self.params[key]
        return cfg

    def make_effect(self, coef: list[float], target: int, state_names: list[str]) -> fx.Effect:
        """The effect object with fitted coefficients, bound to the data's state names."""
        cfg = self.effect_config(coef, target, state_names)
        cls = PhasedDrive if self.params.get("phased") else getattr(fx, self.kind)
        effect = cls(**{k: v for k, v in cfg.items() if k != "_target_"})
        effect.bind(state_names)
        return effect


def node_text(nodes: tuple[int, ...]) -> str:
    """ "node 2" or "nodes 0, 2": where a per-node candidate acts."""
    return f"node {nodes[0]}" if len(nodes) == 1 else "nodes " + ", ".join(str(n) for n in nodes)


class PhasedDrive(fx.Effect):
    """A·sin(ω t + φ_b): a drive with one amplitude and frequency but its own phase in every recording b.

    Recordings start at arbitrary times, so a real drive rarely shares its phase across them. The phase belongs
    to the recording, not to the model: rollouts must batch the recordings in the order of `phases` (the
    residual loop fits the phases of held-in records, and estimates those of held-out records from a warm-up
    window). It is a diagnosis term, not an effect a model can carry to new data.

    Args:
        amplitude, omega: A and ω (rad per unit time), shared.
        phases: φ_b, one per recording.
        target: the driven state variable.
    """

    basis = ("sin(wt+phi_b)",)
    uses_time = per_record = True

    def __init__(
        self,
        amplitude: float = 0.0,
        omega: float = 1.0,
        phases: list[float] | None = None,
        target: str | int = 0,
        source: str | int | None = None,
        learnable: bool = True,
    ) -> None:
        super().__init__(amplitude, target, source, learnable)
        self.log_omega = torch.nn.Parameter(torch.tensor(math.log(omega), dtype=torch.float64), requires_grad=learnable)
        self.phases = torch.nn.Parameter(
            torch.tensor(list(phases or [0.0]), dtype=torch.float64), requires_grad=learnable
        )

    @property
    def omega(self) -> float:
        return float(self.log_omega.detach().exp())

    def features(self, t, x, ctx):
        b = x.shape[0]
        if self.phases.numel() != b:
            raise ValueError(f"PhasedDrive has {self.phases.numel()} phases but the batch has {b} recordings.")
        tt = torch.broadcast_to(torch.as_tensor(t).to(x), x.shape[:-1])  # [B, N]
        return torch.sin(self.log_omega.exp().to(x) * tt + self.phases.to(x)[:, None])[..., None]

    def _formula(self, s):
        return f"{float(self.coef.detach()[0]):.4g}·sin({self.omega:.4g}·t + φ_recording)"

    def config(self) -> dict[str, Any]:
        cfg = super().config()
        del cfg["source"]
        amp = cfg.pop("coef")
        return {**cfg, "amplitude": amp, "omega": self.omega, "phases": [float(p) for p in self.phases.detach()]}


def incoherent_frequency(
    r: torch.Tensor,  # [B, T−1, N] residual of one state variable
    t_mid: torch.Tensor,  # [T−1] step midpoints
    pad: int = 16,
) -> float:
    """Angular frequency of the peak of the *mean per-recording* periodogram: a drive whose phase differs
    between recordings cancels in the average residual but not in the average of the recordings' powers."""
    signal = r.double().mean(dim=2)
    signal = signal - signal.mean(dim=1, keepdim=True)
    n = signal.shape[1]
    dt = float((t_mid[-1] - t_mid[0]) / max(n - 1, 1))
    window = torch.hann_window(n, periodic=False, dtype=torch.float64)
    power = torch.fft.rfft(signal * window, n=pad * n, dim=1).abs().pow(2).mean(dim=0)
    freqs = 2 * math.pi * torch.fft.rfftfreq(pad * n, d=dt, dtype=torch.float64)
    lowest = 2 * pad
    omega0 = float(freqs[lowest + int(torch.argmax(power[lowest:]))])
    span = 2 * math.pi / float(t_mid[-1] - t_mid[0])

    def rss(omega: float) -> float:  # sin, cos and an offset per recording, one ω for all
        x = torch.stack([torch.sin(omega * t_mid), torch.cos(omega * t_mid), torch.ones_like(t_mid)], dim=1)
        sol = torch.linalg.lstsq(x, signal.T).solution
        return float((signal.T - x @ sol).pow(2).sum())

    grid = torch.linspace(max(omega0 - span, 1e-6), omega0 + span, 81, dtype=torch.float64)
    values = torch.tensor([rss(float(w)) for w in grid])  # 81 small fits
    k = int(torch.argmin(values))
    lo, hi = float(grid[max(k - 1, 0)]), float(grid[min(k + 1, len(grid) - 1)])
    for _ in range(30):  # ternary search on the bracket
        a, b = lo + (hi - lo) / 3, hi - (hi - lo) / 3
        if rss(a) < rss(b):
            hi = b
        else:
            lo = a
    return 0.5 * (lo + hi)


def phased_columns(data: Trajectories, omega: float) -> torch.Tensor:
    """[B, T−1, N, 2B] step-averaged sin ωt and cos ωt in the two columns of recording b, zero elsewhere."""
    b, n_t, n, _ = data.x.shape
    t = data.t.double()
    waves = torch.stack([torch.sin(omega * t), torch.cos(omega * t)], dim=-1)  # [T, 2]
    cols = torch.zeros(b, n_t, n, 2 * b, dtype=torch.float64)
    idx = torch.arange(b)
    cols[idx, :, :, 2 * idx] = waves[None, :, None, 0].expand(b, n_t, n)
    cols[idx, :, :, 2 * idx + 1] = waves[None, :, None, 1].expand(b, n_t, n)
    return step_average(cols)


def step_average(values: torch.Tensor) -> torch.Tensor:  # values: [B, T, N, K]
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
    phased: dict[int, float] | None = None,
    notes: list[str] | None = None,
    one_signed_friction: bool = False,
    harmonics: tuple[int, ...] = HARMONICS,
) -> list[Candidate]:
    """Evaluate every candidate's basis on `data`.

    A dry-friction candidate whose source never changes sign on `data` beyond its smoothing scale
    (`one_signed_sources`) is left out: there it equals a constant, which the simpler Bias is (no smoothing scale),
    and a term of a state that never reverses is not friction. Why is appended to `notes`.

    Args:
        data: the observed trajectories (uniform time grid for delays).
        omegas: {target index: angular frequency} of forcing candidates (from the residual periodogram);
            one forcing candidate per distinct frequency.
        phased: {target index: angular frequency} of drives with a phase per recording (from the mean
            per-recording periodogram); one candidate per distinct frequency.
        delays: delays of the feedback candidates (multiples of the sampling step).
        kinds: effect class names to include.
        notes: receives one sentence per candidate left out because a simpler kind equals it on these data.
        one_signed_friction: keep dry friction of a one-signed source (the columns of kinds a model already
            expresses, projected out, not named).
        harmonics: the harmonics k of the phase couplings (`HARMONIC_KINDS`), one candidate per k and source.
    """
    d = data.state_dim
    has_edges = data.edge_index.numel() > 0 and bool((data.edge_index >= 0).any())
    out: list[Candidate] = []
    for kind in kinds:
        if (kind in NEEDS_GRAPH and not has_edges) or kind in MODEL_KINDS:
            continue
        cls = getattr(fx, kind)
        if kind == "Bias":
            effect = cls(0.0, target=0).bind(data.state_names)
            out.append(Candidate(kind, None, {}, step_average(evaluate_effect(effect, data))))
        elif kind == "PeriodicForcing":
            for omega in sorted(set((omegas or {}).values())):
                effect = cls(0.0, omega=omega, target=0).bind(data.state_names)
                out.append(Candidate(kind, None, {"omega": omega}, step_average(evaluate_effect(effect, data))))
            if len(data) > 1:
                for omega in sorted(set((phased or {}).values())):
                    out.append(Candidate(kind, None, {"omega": omega, "phased": True}, phased_columns(data, omega)))
        elif kind == "DryFriction":
            # [D] the smoothing scale: what the records resolve of each variable, never sharper than DRY_MIN_SCALE
            spread = data.x.double().reshape(-1, d).std(0)
            eps = torch.maximum(resolution(data.x), DRY_MIN_SCALE * spread)
            one_signed = {} if one_signed_friction else one_signed_sources(data, eps)
            for s in range(d):
                scale = float(eps[s])
                if s in one_signed:
                    if notes is not None:
                        notes.append(one_signed_sources_text(data.state_names[s], scale, one_signed[s]))
                    continue
                effect = cls(0.0, target=0, source=s, scale=scale).bind(data.state_names)
                out.append(Candidate(kind, s, {"scale": scale}, step_average(evaluate_effect(effect, data))))
        elif kind == "DelayedFeedback":
            dt = float(data.t[1] - data.t[0])
            for tau in delays or []:
                m = int(round(tau / dt))
                if m < 1 or m >= data.n_times - 1:
                    continue
                past = delayed(data.x.double(), m)
                for s in range(d):
                    out.append(Candidate(kind, s, {"delay": m * dt}, step_average(past[..., s : s + 1])))
        elif kind in HARMONIC_KINDS:
            for s in range(d):
                for k in harmonics:  # k = 1 keeps its old form: no harmonic key, the same label and config
                    extra = {} if k == 1 else {"harmonic": k}
                    effect = cls(0.0, target=0, source=s, **extra).bind(data.state_names)
                    out.append(Candidate(kind, s, extra, step_average(evaluate_effect(effect, data))))
        else:
            for s in range(d):
                effect = cls(0.0, target=0, source=s).bind(data.state_names)
                out.append(Candidate(kind, s, {}, step_average(evaluate_effect(effect, data))))
    return out


def one_signed_sources(
    data: Trajectories,
    eps: torch.Tensor,  # [D] dry friction's smoothing scale per state variable
) -> dict[int, dict[str, float]]:
    """The state variables that do not show both signs on `data` beyond ±ε: fewer than `DRY_MIN_SIGN_SHARE` of
    their finite samples on the smaller side. {index: min, max, that share, the spread of tanh(s/ε)}."""
    d = data.state_dim
    x = data.x.double().reshape(-1, d)  # [S, D] every sample
    finite = torch.isfinite(x)  # [S, D]
    count = finite.sum(0).clamp(min=1)  # [D]
    above = ((x > eps) & finite).sum(0) / count  # [D] share beyond +ε
    below = ((x < -eps) & finite).sum(0) / count  # [D] share beyond −ε
    minority = torch.minimum(above, below)  # [D]
    big = torch.finfo(torch.float64).max
    lo = torch.where(finite, x, torch.full_like(x, big)).amin(0)  # [D]
    hi = torch.where(finite, x, torch.full_like(x, -big)).amax(0)  # [D]
    th = torch.where(finite, torch.tanh(x / eps), torch.zeros_like(x))  # [S, D]
    mean = th.sum(0) / count  # [D]
    th_std = ((th - mean).pow(2) * finite).sum(0).div(count).sqrt()  # [D] spread of tanh(s/ε)
    return {
        s: {"min": float(lo[s]), "max": float(hi[s]), "minority": float(minority[s]), "tanh_std": float(th_std[s])}
        for s in range(d)
        if bool(finite[:, s].any()) and float(minority[s]) < DRY_MIN_SIGN_SHARE
    }


def one_signed_sources_text(name: str, scale: float, stats: dict[str, float]) -> str:
    """Why DryFriction(`name`) was left out of the library (`stats`: one entry of `one_signed_sources`)."""
    side = "below −ε" if stats["max"] > -stats["min"] else "above +ε"
    where = (
        f"where −c·tanh({name}/ε) is a constant (its spread over the samples {stats['tanh_std']:.2g}) and the "
        "two kinds are indistinguishable: Bias (a constant, fewer parameters, no smoothing scale) covers it"
        if stats["tanh_std"] < DRY_CONSTANT_SPREAD
        else f"where −c·tanh({name}/ε) is a one-sided saturation, not friction, which reverses with the sign of "
        "its source"
    )
    return (
        f"DryFriction({name}) not considered: {name} never changes sign on these data beyond its smoothing scale "
        f"ε = {scale:.3g} (min {stats['min']:.4g}, max {stats['max']:.4g}; {stats['minority']:.1%} of samples "
        f"{side}), {where}"
    )


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
