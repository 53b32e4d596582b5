"""An effect on some nodes only (issue 61, item 5): per-node variants of the shared single-column state terms.

One damped pendulum in a chain is a poor shared term: its one coefficient is spread over every node. The screen
splits each shared single-column candidate (`effects.PER_NODE_KINDS`) into one column per node, keeps the nodes
BIC selects, and offers the variant beside the shared term when it fits better (`per_node_variants`); the
held-out stage rebuilds the variants the screen named (`with_per_node`).
"""

from __future__ import annotations

import math
from typing import Any

import torch

from mpsim.diagnose.library import Candidate, node_text
from mpsim.diagnose.nuisance import project, target_rows
from mpsim.diagnose.residual import Residual
from mpsim.diagnose.select import lstsq, stepwise_bic
from mpsim.effects import PER_NODE_KINDS


def per_node(c: Candidate, nodes: tuple[int, ...]) -> Candidate:
    """The per-node variant of a shared single-column candidate on `nodes`: column j is the shared column masked
    to node nodes[j] (zero on every other node), so each listed node gets a coefficient of its own."""
    basis = c.basis  # [B, T−1, N, 1]
    mask = torch.eye(basis.shape[2], dtype=basis.dtype)[:, list(nodes)]  # [N, M] node n ↦ column of nodes[j]
    return Candidate(c.kind, c.source, dict(c.params), basis * mask, nodes=tuple(nodes))


def with_per_node(library: list[Candidate], diag: Any) -> list[Candidate]:
    """`library` plus the per-node variants the screen added (`Diagnosis.per_node`), rebuilt from its shared
    candidates, so that the held-out stage finds every candidate the screen's findings name."""
    shared = {c.label(diag.state_names): c for c in library if c.nodes is None}
    have = {c.label(diag.state_names) for c in library}
    out = list(library)
    for label, nodes in diag.per_node:
        if label in shared:
            variant = per_node(shared[label], nodes)
            if variant.label(diag.state_names) not in have:
                have.add(variant.label(diag.state_names))
                out.append(variant)
    return out


def per_node_variants(
    library: list[Candidate],
    res: Residual,
    keep: torch.Tensor,  # [B] finite trajectories
    base: torch.Tensor | None,  # [B, T-1, N, D, P] nuisance columns
    searched: list[int],
    names: list[str],
    min_gain: float,
) -> tuple[list[tuple[Candidate, tuple[str, tuple[int, ...]]]], list[str]]:
    """Per-node variants of the shared single-column state terms (`effects.PER_NODE_KINDS`) that beat them by BIC.

    An effect on some nodes only (one damped pendulum in a chain) is a poor shared term: its one coefficient is
    spread over every node. On each searched row the shared candidate's column is split into one column per node
    (`per_node`), and node columns are forward-selected by BIC (each pays for its coefficient, and must explain at least
    `min_gain` of the row), so that the variant keeps only the nodes that carry the effect. If that variant's BIC (fitted alone, nuisance projected
    out) is below the shared candidate's and it explains at least `min_gain` more of the row, it joins the library
    and the joint selection chooses between them.

    Returns:
        ([(the variant, (its shared candidate's label, its nodes))], one sentence per variant for the report).
    """
    n_nodes = res.r.shape[2]
    eligible = [c for c in library if c.nodes is None and c.kind in PER_NODE_KINDS and c.basis.shape[-1] == 1]
    if n_nodes < 2 or not eligible:
        return [], []
    every = tuple(range(n_nodes))
    split = [per_node(c, every) for c in eligible]  # each [B, T-1, N, N]
    out: list[tuple[Candidate, tuple[str, tuple[int, ...]]]] = []
    notes: list[str] = []
    have: set[str] = set()
    for d in searched:  # a few state rows
        y, groups, base_d = target_rows(eligible + split, res, d, keep, base)
        y, groups = project(y, groups, base_d)
        flat = y.reshape(-1)  # [n] residual samples
        n = flat.numel()
        if n == 0 or float(flat.pow(2).sum()) == 0.0:
            continue
        m = len(eligible)
        for c, shared, cols in zip(eligible, groups[:m], groups[m:], strict=True):  # candidates, not nodes
            _, rss_shared = lstsq(shared.reshape(n, 1), flat)
            bic_shared = n * math.log(max(rss_shared, 1e-300) / n) + math.log(n)
            per = cols.reshape(n, n_nodes)  # [n, N] node n's column
            sel = stepwise_bic(flat, list(per[:, :, None].unbind(1)), max_terms=n_nodes)
            # a node is kept only if its column explains at least `min_gain` of the row, as an effect must: on
            # clean data BIC also admits the neighbours of a damped node, whose columns take up the step's
            # O(Δ²) echo of its damping through the springs (coefficients ~1e-3 of the node's own)
            nodes = tuple(sorted(g for g in sel.groups if sel.gains[g] >= min_gain))
            if not nodes:
                continue
            _, rss_nodes = lstsq(per[:, list(nodes)], flat)
            bic_nodes = n * math.log(max(rss_nodes, 1e-300) / n) + len(nodes) * math.log(n)
            # and what the split adds over the shared coefficient must itself be an effect's share: on clean data a
            # chain damped alike on every node fits 4 coefficients (0.299 each) better than one by BIC alone
            if bic_nodes >= bic_shared or (rss_shared - rss_nodes) < min_gain * float(flat.pow(2).sum()):
                continue
            variant = per_node(c, nodes)
            label = variant.label(names)
            every_coef, _ = lstsq(per, flat)  # [N] every node's own coefficient, for the report
            kept = ", ".join(f"node {k}: {float(every_coef[k]):.3g}" for k in nodes)
            others = ", ".join(f"node {k}: {float(every_coef[k]):.2g}" for k in every if k not in nodes)
            notes.append(
                f"d{names[d]}/dt: {c.label(names)} fits better per node — on {node_text(nodes)} only "
                f"({kept}{'; the others ≈ 0: ' + others if others else ''}), BIC {bic_nodes:.1f} against "
                f"{bic_shared:.1f} with one coefficient shared by all {n_nodes} nodes: {label} is a candidate"
            )
            if label not in have:
                have.add(label)
                out.append((variant, (c.label(names), nodes)))
    return out, notes
