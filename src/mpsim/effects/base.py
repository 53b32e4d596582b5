"""The base class and the effects that read the state alone; time and delays are in `temporal`, the couplings in
`couplings`. See the package's docstring (`mpsim.effects`)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from mpsim.errors import ConfigError
from mpsim.graphs.batch import BatchedGraph, batch_graph


@dataclass
class EffectContext:
    """What an effect may read besides (t, x): the batched coupling graph and, for delays, the history.

    Attributes:
        graph: B graphs of N nodes flattened (see `mpsim.graphs.batch_graph`).
        history: `history(t_query) -> [B, N, D]` states at an earlier time (None when unavailable).
    """

    graph: BatchedGraph
    history: Callable[[torch.Tensor], torch.Tensor] | None = None

    @staticmethod
    def for_batch(
        edge_index: torch.Tensor,  # [2, E] or [B, 2, E] coupling graph
        x: torch.Tensor,  # [B, N, D] states (for the batch size, device and dtype)
        history: Callable[[torch.Tensor], torch.Tensor] | None = None,
    ) -> EffectContext:
        b, n, _ = x.shape
        return EffectContext(batch_graph(edge_index.to(x.device), b, n, dtype=x.dtype), history)


def _resolve(ref: str | int, names: Sequence[str], what: str, effect: str) -> int:
    if isinstance(ref, int):
        if not 0 <= ref < len(names):
            raise ConfigError(f"{effect}.{what}={ref} is out of range for state variables {list(names)}.")
        return ref
    if ref not in names:
        raise ConfigError(f"{effect}.{what}={ref!r} is not a state variable; choose one of {list(names)}.")
    return list(names).index(ref)


class Effect(nn.Module):
    """Base class. Subclasses define `basis` (the names of their basis functions), `features` and, when the
    term is not linear in its parameters, `forward`.

    Args:
        coef: initial coefficient(s), one per basis function.
        target: the state variable whose derivative receives the term (name or index).
        source: the state variable the term reads (default: the target).
        learnable: whether the coefficients are trained.
    """

    basis: tuple[str, ...] = ("phi",)
    #: the term reads absolute time (a drive) or the record's place in the batch; most read states only
    uses_time: bool = False
    #: the term reads the record's place in the batch (a phase per recording): records may not be tiled or reordered
    per_record: bool = False

    def __init__(
        self,
        coef: float | Sequence[float] = 0.0,
        target: str | int = 0,
        source: str | int | None = None,
        learnable: bool = True,
        nodes: Sequence[int] | None = None,
    ) -> None:
        super().__init__()
        self.nodes = _check_nodes(nodes, type(self).__name__, len(self.basis))
        width = len(self.basis) if self.nodes is None else len(self.nodes)
        values = [float(coef)] * width if isinstance(coef, int | float) else [float(c) for c in coef]
        if len(values) != width:
            what = "basis function" if self.nodes is None else f"listed node (nodes={self.nodes})"
            raise ConfigError(f"{type(self).__name__} needs {width} coefficient(s), one per {what}; got {len(values)}.")
        self.coef = nn.Parameter(torch.tensor(values, dtype=torch.float64), requires_grad=learnable)
        self.target_ref, self.source_ref = target, target if source is None else source
        self.target = target if isinstance(target, int) else None
        self.source = self.source_ref if isinstance(self.source_ref, int) else None

    @property
    def name(self) -> str:
        return type(self).__name__

    def bind(self, state_names: Sequence[str]) -> Effect:
        """Resolve target/source names to indices for data with these state variables."""
        self.target = _resolve(self.target_ref, state_names, "target", self.name)
        self.source = _resolve(self.source_ref, state_names, "source", self.name)
        self.state_names = list(state_names)
        return self

    def _check_bound(self) -> None:
        if self.target is None or self.source is None:
            raise ConfigError(f"{self.name}: call bind(state_names) before use (target={self.target_ref!r}).")

    def features(
        self,
        t: torch.Tensor,  # [] time
        x: torch.Tensor,  # [B, N, D] states (raw units)
        ctx: EffectContext,
    ) -> torch.Tensor:
        """[B, N, K] the K basis functions of this effect at each node."""
        raise NotImplementedError

    def forward(
        self,
        t: torch.Tensor,  # [] time
        x: torch.Tensor,  # [B, N, D] states (raw units)
        ctx: EffectContext,
    ) -> torch.Tensor:
        """[B, N, D] the term added to dx/dt (zero except in the target column)."""
        self._check_bound()
        if self.nodes is None:
            term = (self.features(t, x, ctx) * self.coef.to(x)).sum(-1)  # [B, N]
        else:
            term = self.features(t, x, ctx)[..., 0] * self.node_coef(x.shape[1]).to(x)  # [B, N]
        out = torch.zeros_like(x)
        out[..., self.target] = term
        return out

    def node_coef(self, n: int) -> torch.Tensor:
        """[N] the coefficient of each of n nodes: the listed nodes' own, zero on the others (or the shared one)."""
        if self.nodes is None:
            return self.coef[:1].expand(n)
        if max(self.nodes) >= n:
            raise ConfigError(f"{self.name}: nodes={list(self.nodes)} but the graph has {n} node(s) (0 to {n - 1}).")
        idx = torch.as_tensor(self.nodes, device=self.coef.device)  # [M] listed nodes
        return torch.zeros(n, dtype=self.coef.dtype, device=self.coef.device).index_add(0, idx, self.coef)

    def describe(self) -> str:
        """A readable formula with the current coefficients (a per-node term: each listed node's)."""
        names = getattr(self, "state_names", None)
        s = names[self.source] if names and self.source is not None else str(self.source_ref)
        tgt = names[self.target] if names and self.target is not None else str(self.target_ref)
        if self.nodes is None:
            return f"d{tgt}/dt += {self._formula(s)}"
        coefs = [float(c) for c in self.coef.detach()]
        terms = "; ".join(f"node {n}: {self._term(s, c)}" for n, c in zip(self.nodes, coefs, strict=True))
        return f"d{tgt}/dt += {terms} (other nodes: 0)"

    def _formula(self, s: str) -> str:
        return self._term(s, float(self.coef.detach()[0]))

    def _term(self, s: str, c: float) -> str:
        """The formula of a single-basis term with coefficient c."""
        return f"{c:+.4g}·{self.basis[0]}({s})"

    def config(self) -> dict[str, Any]:
        """The Hydra config that rebuilds this effect with its current coefficients."""
        coef = [float(c) for c in self.coef.detach()]
        nodes = {} if self.nodes is None else {"nodes": list(self.nodes)}
        return {
            "_target_": f"{_public_module(type(self))}.{type(self).__qualname__}",
            "coef": coef if len(coef) > 1 or nodes else coef[0],
            **nodes,
            "target": self.state_names[self.target]
            if self.target is not None and hasattr(self, "state_names")
            else self.target_ref,
            "source": self.state_names[self.source]
            if self.source is not None and hasattr(self, "state_names")
            else self.source_ref,
        }

    def extra_repr(self) -> str:
        nodes = "" if self.nodes is None else f", nodes={self.nodes}"
        return f"target={self.target_ref}, source={self.source_ref}, coef={[round(float(c), 6) for c in self.coef.detach()]}{nodes}"


class LinearDamping(Effect):
    """−c·s: viscous friction when s is a velocity (target = source = velocity)."""

    basis = ("-s",)

    def features(self, t, x, ctx):
        return -x[..., self.source : self.source + 1]

    def _term(self, s, c):
        return f"{_minus_c(c)}·{s}"


class QuadraticDrag(Effect):
    """−c·s·|s|: aerodynamic drag."""

    basis = ("-s|s|",)

    def features(self, t, x, ctx):
        s = x[..., self.source : self.source + 1]
        return -s * s.abs()

    def _term(self, s, c):
        return f"{_minus_c(c)}·{s}·|{s}|"


class DryFriction(Effect):
    """−c·tanh(s/ε): Coulomb (dry) friction of magnitude c, its sign(s) smoothed over the velocity scale ε.

    Args:
        coef: c, the friction force (per unit mass).
        target: the state variable whose derivative receives the term (the velocity).
        source: the state variable the term reads (default: the target).
        scale: ε > 0, the smoothing scale in the source's units (fixed, not trained); smaller is sharper.
        learnable: whether c is trained.
    """

    basis = ("-tanh(s/eps)",)

    def __init__(
        self,
        coef: float | Sequence[float] = 0.0,
        target: str | int = 0,
        source: str | int | None = None,
        scale: float = 0.01,
        learnable: bool = True,
        nodes: Sequence[int] | None = None,
    ) -> None:
        super().__init__(coef, target, source, learnable, nodes)
        if isinstance(scale, bool) or not isinstance(scale, int | float) or not scale > 0 or math.isinf(scale):
            raise ConfigError(
                f"DryFriction.scale must be a finite number > 0 (the velocity over which sign(v) is "
                f"smoothed, e.g. scale=0.01); got {scale!r}."
            )
        self.scale = float(scale)

    def features(self, t, x, ctx):
        return -torch.tanh(x[..., self.source : self.source + 1] / self.scale)

    def _term(self, s, c):
        return f"{_minus_c(c)}·tanh({s}/{self.scale:g})"

    def config(self) -> dict[str, Any]:
        return {**super().config(), "scale": self.scale}


class CubicStiffness(Effect):
    """−c·s³: a hardening spring (Duffing) term."""

    basis = ("-s^3",)

    def features(self, t, x, ctx):
        return -x[..., self.source : self.source + 1].pow(3)

    def _term(self, s, c):
        return f"{_minus_c(c)}·{s}³"


class Bias(Effect):
    """A constant c (an offset, a constant external force)."""

    basis = ("1",)

    def features(self, t, x, ctx):
        return torch.ones_like(x[..., :1])

    def _term(self, s, c):
        return f"{c:+.4g}"


def _public_module(cls: type) -> str:
    """Where configs name an effect class: `mpsim.effects` for the package's own (defined in its submodules)."""
    module = cls.__module__
    return "mpsim.effects" if module.startswith("mpsim.effects.") else module


def _minus_c(c: float) -> str:
    """ "−c" of the coefficient c of a term −c·φ with one clean sign: −0.3 for c = 0.3, +0.02 for c = −0.02."""
    return f"-{c:.4g}" if c >= 0 else f"+{-c:.4g}"


#: the kinds that may act on some nodes only (`nodes=[...]`, a coefficient per listed node): one basis function
#: of the node's own state (the screen offers a per-node variant of each, `mpsim.diagnose.pernode.per_node`)
PER_NODE_KINDS = ("Bias", "LinearDamping", "QuadraticDrag", "CubicStiffness", "DryFriction")


def _check_nodes(nodes: Sequence[int] | None, effect: str, n_basis: int) -> tuple[int, ...] | None:
    """The listed nodes as a sorted tuple of distinct indices ≥ 0 (None: the term acts on every node, shared)."""
    if nodes is None:
        return None
    if effect not in PER_NODE_KINDS or n_basis != 1:
        raise ConfigError(f"{effect} has no per-node form (nodes=...); only {list(PER_NODE_KINDS)} do.")
    if isinstance(nodes, int | str) or not all(isinstance(n, int) and not isinstance(n, bool) for n in nodes):
        raise ConfigError(f"{effect}.nodes must be a list of node indices, e.g. nodes=[2]; got {nodes!r}.")
    out = tuple(int(n) for n in nodes)
    if not out or min(out) < 0 or len(set(out)) != len(out) or list(out) != sorted(out):
        raise ConfigError(f"{effect}.nodes must list distinct node indices ≥ 0 in increasing order; got {list(out)}.")
    return out


def total(
    effects: Sequence[Effect] | nn.ModuleList, t: torch.Tensor, x: torch.Tensor, ctx: EffectContext
) -> torch.Tensor:
    """[B, N, D] sum of the effects' terms (zeros when there are none); `effects` may be a model's ModuleList."""
    out = torch.zeros_like(x)
    for effect in effects:  # a handful of named terms, not a loop over nodes
        out = out + effect(t, x, ctx)
    return out
