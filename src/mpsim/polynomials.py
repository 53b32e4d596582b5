"""Monomials of state variables: the one generator, used by S-MNN equation discovery's basis library and by the
residual loop's nuisance columns (the polynomials a model can already express)."""

from __future__ import annotations

import itertools

import torch


def monomials(n_vars: int, degree: int) -> list[tuple[int, ...]]:
    """Variable-index tuples of every monomial of degree ≤ `degree`, graded (pysindy/reference order): (),
    (0,), (1,), …, (0, 0), (0, 1), …"""
    return [c for d in range(degree + 1) for c in itertools.combinations_with_replacement(range(n_vars), d)]


def monomial_features(
    x: torch.Tensor,  # [..., D] state variables
    degree: int,
) -> torch.Tensor:
    """[..., K] every monomial of the last axis's variables of degree 1..`degree`, in `monomials` order."""
    higher = [m for m in monomials(x.shape[-1], degree) if len(m) > 1]
    if not higher:
        return x
    return torch.cat([x, torch.stack([x[..., list(m)].prod(-1) for m in higher], dim=-1)], dim=-1)
