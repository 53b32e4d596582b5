"""The term library of S-MNN discovery: monomials by name, and the polynomial vector field they span.

A library term is a tuple of state-variable indices (`mpsim.polynomials.monomials`: () is the constant,
(0, 2) is x z); `monomial_name` and `parse_monomial` translate between terms and the names users write
("x^3", "x y^2"), `resolve_terms` builds the library from a degree and extra terms, `equation_text` prints one
discovered equation, and `PolynomialField` is dx/dt = φ(x) ξ (+ effects) for the ODE solver.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol

import torch
from torch import nn

from mpsim.effects import EffectContext, total
from mpsim.errors import ConfigError
from mpsim.polynomials import monomials


def monomial_name(term: tuple[int, ...], names: Sequence[str]) -> str:
    """ "1", "x", "x^2", "x z" for the index tuple of a monomial."""
    if not term:
        return "1"
    return " ".join(names[v] + (f"^{p}" if p > 1 else "") for v, p in sorted({v: term.count(v) for v in term}.items()))


def parse_monomial(text: str) -> list[tuple[str, int]]:
    """[(name, power), ...] of a monomial written "x^3", "x y^2" or "x*y*z" (names of state variables); "x**3"
    is read as "x^3" (Hydra's command-line grammar takes it unquoted: model.extra_terms=[x**3])."""
    factors = []
    for token in text.replace("**", "^").replace("*", " ").split():
        name, _, power = token.partition("^")
        if not name or (power and not power.isdigit()) or (power and int(power) < 1):
            raise ConfigError(f'model.extra_terms: cannot read {text!r}; write monomials like "x^3", "x y^2" or "x*z".')
        factors.append((name, int(power) if power else 1))
    if not factors:
        raise ConfigError(f'model.extra_terms: {text!r} is empty; write monomials like "x^3".')
    return factors


def resolve_terms(
    state_dim: int,
    degree: int,
    extra_terms: Sequence[str],
    extra: Sequence[list[tuple[str, int]]],  # `parse_monomial` of each extra term
    names: Sequence[str],
    strict: bool,
) -> list[tuple[int, ...]] | None:
    """The library: every monomial of degree ≤ `degree`, then the extra terms under `names`.

    Returns None when an extra term names an unknown variable and `strict` is False (names not known yet).

    Raises:
        ConfigError: an unknown name with `strict`, or an extra term already in the library.
    """
    terms = monomials(state_dim, degree)
    for text, factors in zip(extra_terms, extra, strict=True):
        unknown = [name for name, _ in factors if name not in names]
        if unknown:
            if strict:
                raise ConfigError(
                    f"model.extra_terms: {text!r} names {unknown}, not state variables; choose from {list(names)}."
                )
            return None
        term = tuple(sorted(i for name, p in factors for i in [names.index(name)] * p))
        if term in terms:
            raise ConfigError(
                f"model.extra_terms: {text!r} is already in the library (degree {degree}) or listed twice."
            )
        terms.append(term)
    return terms


def gather_index(terms: Sequence[tuple[int, ...]], state_dim: int) -> list[list[int]]:
    """[n_terms, width] the library as a gather from [x, 1]: the constant slot (index D) pads lower-degree
    terms (gradient-safe, no pow)."""
    width = max(len(term) for term in terms)
    return [list(term) + [state_dim] * (width - len(term)) for term in terms]


def equation_text(parts: Sequence[tuple[float, str]], digits: int) -> str:
    """ "-10.000 x + 10.000 y" from (coefficient, term name) pairs; "0" when there are none."""
    text = ""
    for k, (c, term) in enumerate(parts):
        sign = ("-" if c < 0 else "") if k == 0 else (" - " if c < 0 else " + ")
        text += f"{sign}{abs(c):.{digits}f}" + ("" if term == "1" else f" {term}")
    return text or "0"


class _LibraryModel(Protocol):
    """What the field reads of its model (`SMNNDiscovery`): the term library and the effects."""

    effects: Any

    def library(self, x: torch.Tensor) -> torch.Tensor: ...  # x: [B, N, D] -> [B, N, n_terms]


class PolynomialField(nn.Module):
    """dx/dt = φ(x) ξ + Σ effects (ξ fixed during one solve), optionally in a rescaled time.

    With `scale` and `start`, each trajectory b runs in τ ∈ [0, 1] over its own step: t = start_b + τ·scale_b
    and dx/dτ = scale_b · dx/dt (the one-step predictions of `SMNNDiscovery.one_step`).
    """

    def __init__(
        self,
        model: _LibraryModel,
        xi: torch.Tensor,  # [n_terms, D] coefficients
        graph: Any = None,  # BatchedGraph of the batch (effects that read neighbours), or None
        scale: torch.Tensor | None = None,  # [B, 1, 1] step length per trajectory (None: plain time)
        start: torch.Tensor | None = None,  # [B, 1] start time per trajectory (with scale)
    ) -> None:
        super().__init__()
        self.model, self.xi, self.graph, self.scale, self.start = model, xi, graph, scale, start

    def forward(self, t: torch.Tensor, x: torch.Tensor, history=None) -> torch.Tensor:  # t: [], x: [B, N, D]
        dx = self.model.library(x) @ self.xi
        if len(self.model.effects):
            if self.scale is None:
                when = t  # []
            else:
                assert self.start is not None  # given with `scale`
                when = self.start + t * self.scale[..., 0]  # [B, 1]
            dx = dx + total(self.model.effects, when, x, EffectContext(self.graph, history))
        return dx if self.scale is None else self.scale * dx
