"""Graph-network blocks shared by the N-body models (DeltaGN, HOGN) on full, kNN and hierarchical graphs.

Widths and activations follow Martinkus et al. (AAAI 2021), Appendix B, and the reference code (spec §3):

- every MLP applies its activation after *every* layer, the last included (a separate linear layer decodes);
- edge blocks φe: 2 × 150; node blocks φv: 3 × 100; global block φu (HOGN): 2 × 100;
- hierarchy: φp→c and φcc→cp (upward) 2 × 100; φc→c and φcp→cc (downward interactions) 2 × 150;
  φc (cell update) 3 × 100; φc→p (the long-range edge into each particle) 2 × 150;
- ReLU for the DeltaGN family, Softplus for HOGN (ReLU's piecewise-constant derivative would make HOGN's
  forces piecewise constant).

All aggregations are sums over segments (`index_add`), over the flattened batch: particle i of sample b is
node b*N + i, cells carry compact ids over the whole batch. No Python loop runs over particles, cells or
edges; the only loops are over the ~log4 N hierarchy levels, the 3-4 input parts of an MLP, and tiles of a few
thousand edges (`MLP.segment_sum_parts`: an edge MLP and its sum per receiver never hold all edges' [E, 150]
intermediates at once, so the time per edge stays flat as N grows).

Every edge MLP computes its first layer per *node* and gathers the result onto the edges
(`MLP.forward_parts`): W [x_s, x_r, d] = W_s x_s + W_r x_r + W_d d, which is the same function and the
same parameters as the concatenated input, but costs O(nodes · in · H + edges · H) instead of
O(edges · in · H) — 2-20x less for the full graph and the 100-200-wide cell embeddings.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn

from mpsim.graphs.hierarchy import Hierarchy
from mpsim.models.layers import activation, linear_stack
from mpsim.periodic import minimum_image

# Paper widths (Appendix B): (width, layers) per block.
EDGE = (150, 2)
NODE = (100, 3)
GLOBAL = (100, 2)
UP = (100, 2)
DOWN = (150, 2)
CELL = (100, 3)
CELL_TO_PARTICLE = (150, 2)

# Rows (edges) per tile of `MLP.segment_sum_parts`: 4096 x 150 float32 = 2.4 MB per intermediate, which stays in
# a CPU's cache (hierarchical DeltaGN at N = 10^5, one thread: tiles of 1024-16384 rows within the machine's noise,
# untiled 1.7-2.4x slower); a GPU wants large tiles.
_TILE_ROWS = 4096
_TILE_ROWS_CUDA = 1 << 22

# An input part of an MLP: (values [n, f], index [E] gathering them onto the rows, or None if already per row
# or a single broadcast row [1, f]).
Part = tuple[torch.Tensor, torch.Tensor | None]


class MLP(nn.Module):
    """`n_layers` × (Linear + activation), the activation after every layer (the reference's blocks).

    Args:
        n_in: input width.
        width: hidden width (also the output width).
        n_layers: number of Linear layers.
        act: activation name.
    """

    def __init__(self, n_in: int, width: int, n_layers: int, act: str) -> None:
        super().__init__()
        sizes = [n_in] + [width] * n_layers
        self.layers = nn.ModuleList(linear_stack(sizes))
        self.act = activation(act)
        self.n_in, self.width = n_in, width

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # x: [R, n_in] rows
        """[R, width]."""
        for layer in self.layers:
            x = self.act(layer(x))
        return x

    def _first_layer(self) -> nn.Linear:
        first = self.layers[0]
        assert isinstance(first, nn.Linear)  # `linear_stack` builds it; ModuleList items are typed as Module
        return first

    def forward_parts(self, parts: Sequence[Part], n_rows: int | None = None) -> torch.Tensor:
        """[R, width] the MLP of the row-wise concatenation of `parts`, without building it.

        Each part is (values [n_k, f_k], index [R] or None): indexed parts are projected per node and then
        gathered onto the R rows (edges); unindexed parts are either per row [R, f_k] or one broadcast row
        [1, f_k] (the constant dt feature). The widths f_k must add up to `n_in`, in input order.
        """
        return self._rows(self._project(parts), None, n_rows)

    def segment_sum_parts(
        self,
        parts: Sequence[Part],
        segment: torch.Tensor,  # [R] segment (receiver) of each row
        n_segments: int,
    ) -> torch.Tensor:
        """[n_segments, width] Σ per segment of the rows of `forward_parts(parts)`, in tiles of rows.

        The same sums as `graphs.batch.segment_sum(forward_parts(parts), segment, n_segments)`, but the R rows (edges) are
        run through the MLP a tile at a time and summed into the output at once: the per-row intermediates
        (R x 150 floats each, 0.8 GB at R = 1.4 M) never exist whole. Whole-graph intermediates cost page faults
        on every fresh allocation and a trip through main memory per layer; tiles stay in the CPU cache, which
        keeps the time per edge flat from N = 10^3 to 10^5. A GPU gets tiles large enough to fill it.
        """
        projected = self._project(parts)
        n_rows = int(segment.shape[0])
        out = self._first_layer().weight.new_zeros(n_segments, self.width)
        tile = _TILE_ROWS_CUDA if segment.is_cuda else _TILE_ROWS
        for r0 in range(0, n_rows, tile):  # a loop over tiles of edges, not over edges
            rows = slice(r0, min(n_rows, r0 + tile))
            out.index_add_(0, segment[rows], self._rows(projected, rows, rows.stop - rows.start))
        return out

    def _project(self, parts: Sequence[Part]) -> list[tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]]:
        """Per part: (values @ W_k^T [n_k, H], index, None) for indexed parts and broadcast rows (the first layer
        once per node, not once per row), or (values [R, f_k], None, W_k [H, f_k]) for per-row parts, which
        `_rows` projects a tile at a time."""
        first = self._first_layer()
        col = 0
        out: list[tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]] = []
        for values, index in parts:
            f = values.shape[-1]
            weight = first.weight[:, col : col + f]
            per_row = index is None and values.shape[0] != 1
            out.append((values, None, weight) if per_row else (values @ weight.T, index, None))
            col += f
        if col != self.n_in:
            raise ValueError(f"MLP expects {self.n_in} input features; the parts give {col}.")
        return out

    def _rows(
        self,
        projected: Sequence[tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]],  # from `_project`
        rows: slice | None,  # the rows to compute (None: all)
        n_rows: int | None,  # number of rows computed (to broadcast a result that has one row)
    ) -> torch.Tensor:
        """[n_rows, width] the MLP of `rows` from the first layer's per-part projections."""
        h = None
        for values, index, weight in projected:
            if weight is not None:  # a per-row part: project the rows of this tile
                proj = (values if rows is None else values[rows]) @ weight.T
            elif index is not None:  # a per-node part: gather its projection onto the rows
                proj = values.index_select(0, index if rows is None else index[rows])
            else:  # one broadcast row
                proj = values
            h = proj if h is None else h + proj
        assert h is not None  # `_project` checked that the parts give n_in > 0 features
        h = h + self._first_layer().bias
        if n_rows is not None and h.shape[0] != n_rows:
            h = h.expand(n_rows, -1)
        h = self.act(h)
        for layer in self.layers[1:]:
            h = self.act(layer(h))
        return h


@dataclass(frozen=True)
class ParticleEdges:
    """The particle-particle edges a GN block runs on (full, kNN, or a hierarchy's lowest level).

    Node ids are in *graph order*: the particles may have been renumbered along a space-filling curve before the
    graph was built (`ParticleModel.build_graph`), so that the gathers and segment sums of a forward pass touch
    memory almost sequentially. Graph node b*N + j is then the caller's particle ``order[b*N + j]`` (always one
    of sample b's); `to_graph_order` and `to_caller_order` convert per-particle values.

    Attributes:
        edge_index: [2, E] (sender, receiver) flattened particle ids b*N + j, in graph order.
        n_graphs: B samples.
        n_particles: N particles per sample.
        hierarchy: the quadtree the edges come from (its particle ids in graph order too), or None for flat graphs.
        order: [B*N] the caller's flattened particle id of each graph node, or None when both orders are the same.
    """

    edge_index: torch.Tensor
    n_graphs: int
    n_particles: int
    hierarchy: Hierarchy | None = None
    order: torch.Tensor | None = None

    @property
    def n_nodes(self) -> int:
        return self.n_graphs * self.n_particles

    @functools.cached_property
    def inverse(self) -> torch.Tensor | None:
        """[B*N] the graph node of each caller's particle (the inverse permutation of `order`), or None."""
        if self.order is None:
            return None
        inv = torch.empty_like(self.order)
        inv[self.order] = torch.arange(self.order.shape[0], device=self.order.device)
        return inv

    def to_graph_order(self, values: torch.Tensor) -> torch.Tensor:  # values: [B, N, F] in the caller's order
        """[B, N, F] the same per-particle values, in graph order (differentiable)."""
        return take_rows(values, self.order)

    def to_caller_order(self, values: torch.Tensor) -> torch.Tensor:  # values: [B, N, F] in graph order
        """[B, N, F] per-particle values computed in graph order, back in the caller's order (differentiable)."""
        return take_rows(values, self.inverse)

    def vectors(self, pos: torch.Tensor, box_size: float) -> torch.Tensor:  # pos: [P, 2] flattened positions
        """[E, 2] minimum-image x_sender - x_receiver (differentiable in `pos`)."""
        return minimum_image(pos[self.edge_index[0]] - pos[self.edge_index[1]], box_size)


def take_rows(
    values: torch.Tensor,  # [B, N, F] per-particle values
    index: torch.Tensor | None,  # [B*N] flattened source row of each output row, or None (identity)
) -> torch.Tensor:
    """[B, N, F] the rows of `values` (flattened over B*N) taken in the order `index` (a permutation within
    samples); `values` itself when `index` is None."""
    if index is None:
        return values
    return values.reshape(-1, values.shape[-1]).index_select(0, index).reshape(values.shape)


class HierarchyPass(nn.Module):
    """Upward and downward passes through the quadtree: one long-range edge embedding per particle.

    Upward: e_c = [V_c, Σ_p φp→c(V_p, V_c, x_p - X_c)] at the lowest level, then
    e_parent = [V_parent, Σ_child φcc→cp(e_child, V_parent, X_child - X_parent)] (φcc→cp shared by levels).
    Downward, from the top (4x4) level: messages φc→c(e_s, e_r, X_s - X_r) over the near-neighbour edges plus,
    below the top, one message φcp→cc(s_parent, e_c, X_parent - X_c) from the parent's new state; their sum
    updates s_c = [V_c, φc(e_c, Σ)] (φc→c, φcp→cc and φc shared by levels). Finally each particle receives
    φc→p(s_c, V_p, X_c - x_p) from its lowest cell. The raw cell features V_c stay in every state, the learned
    part is replaced (reference `HierarchicalDeltaGN`). With `dt` given, every MLP also sees the constant step.

    Args:
        d: non-position features per particle and per cell (3 for gravity, 4 with charge).
        act: activation name.
        dt_feature: whether each MLP gets the time step as an extra input.
    """

    def __init__(self, d: int, act: str, dt_feature: bool) -> None:
        super().__init__()
        k = int(dt_feature)
        e = d + UP[0]  # an upward cell embedding [V_c, Σ]
        self.up_particle = MLP(2 * d + 2 + k, UP[0], UP[1], act)  # φp→c
        self.up_cell = MLP(e + d + 2 + k, UP[0], UP[1], act)  # φcc→cp
        self.near = MLP(2 * e + 2 + k, DOWN[0], DOWN[1], act)  # φc→c
        self.down_cell = MLP(2 * e + 2 + k, DOWN[0], DOWN[1], act)  # φcp→cc
        self.update = MLP(e + DOWN[0] + k, CELL[0], CELL[1], act)  # φc
        self.to_particle = MLP(e + d + 2 + k, CELL_TO_PARTICLE[0], CELL_TO_PARTICLE[1], act)  # φc→p
        self.out_width = CELL_TO_PARTICLE[0]

    def forward(
        self,
        hierarchy: Hierarchy,
        particle_feats: torch.Tensor,  # [P, d] particle features (no positions)
        particle_pos: torch.Tensor,  # [P, 2] particle positions
        cell_feats: Sequence[torch.Tensor],  # per level, lowest first: [C_l, d] cell features (no positions)
        cell_pos: Sequence[torch.Tensor],  # per level: [C_l, 2] cell centres of mass
        dt: torch.Tensor | None = None,  # [1, 1] time step feature, or None
    ) -> torch.Tensor:
        """[P, 150] the edge embedding from each particle's lowest cell (all its long-range interactions)."""
        box = hierarchy.box_size
        extra: list[tuple[torch.Tensor, None]] = [] if dt is None else [(dt, None)]
        levels = hierarchy.cells
        n_levels = len(levels)

        # upward pass: particles -> lowest cells -> ... -> top level
        pc = hierarchy.particle_cell  # [P]
        n_p = particle_feats.shape[0]
        vec = minimum_image(particle_pos - cell_pos[0][pc], box)  # [P, 2] x_p - X_c
        up = self.up_particle.segment_sum_parts(
            [(particle_feats, None), (cell_feats[0], pc), (vec, None), *extra], pc, levels[0].n_cells
        )
        embed = [torch.cat([cell_feats[0], up], dim=-1)]  # [C_0, d+100]
        for lv in range(n_levels - 1):
            parent = levels[lv].parent  # [C_lv] parent id of each cell
            assert parent is not None  # every level below the top has one
            vec = minimum_image(cell_pos[lv] - cell_pos[lv + 1][parent], box)  # X_child - X_parent
            up = self.up_cell.segment_sum_parts(
                [(embed[lv], None), (cell_feats[lv + 1], parent), (vec, None), *extra], parent, levels[lv + 1].n_cells
            )
            embed.append(torch.cat([cell_feats[lv + 1], up], dim=-1))

        # downward pass: near-neighbour interactions at every level, plus the parent's message below the top
        state: torch.Tensor | None = None  # new state of the level above
        for lv in reversed(range(n_levels)):
            level, e = levels[lv], embed[lv]
            snd, rcv = level.edge_index
            vec = minimum_image(cell_pos[lv][snd] - cell_pos[lv][rcv], box)  # X_s - X_r
            incoming = self.near.segment_sum_parts([(e, snd), (e, rcv), (vec, None), *extra], rcv, level.n_cells)
            if state is not None:
                parent = level.parent
                vec = minimum_image(cell_pos[lv + 1][parent] - cell_pos[lv], box)  # X_parent - X_child
                incoming = incoming + self.down_cell.forward_parts(
                    [(state, parent), (e, None), (vec, None), *extra], level.n_cells
                )
            upd = self.update.forward_parts([(e, None), (incoming, None), *extra], level.n_cells)
            state = torch.cat([cell_feats[lv], upd], dim=-1)  # [C, d+100]

        # lowest cell -> particle: the one edge that carries every long-range interaction
        assert state is not None  # a hierarchy has at least one level
        vec = minimum_image(cell_pos[0][pc] - particle_pos, box)  # X_c - x_p
        return self.to_particle.forward_parts([(state, pc), (particle_feats, None), (vec, None), *extra], n_p)


class InteractionBlock(nn.Module):
    """Edge and node blocks of a GN on the particle graph, optionally with the hierarchy's extra edge.

    Edges: e_k = φe(V_s, V_r, x_s - x_r [, dt]); nodes: v_i = φv(V_i, Σ_{k→i} e_k + e_{c→i} [, dt]).

    Args:
        d: non-position particle features.
        act: activation name.
        dt_feature: append the time step to every MLP input (the reference DeltaGN's constant feature).
        hierarchical: build the `HierarchyPass` (its φc→p edge joins each particle's sum).
    """

    def __init__(self, d: int, act: str, dt_feature: bool, hierarchical: bool) -> None:
        super().__init__()
        k = int(dt_feature)
        self.edge = MLP(2 * d + 2 + k, EDGE[0], EDGE[1], act)  # φe
        self.node = MLP(d + EDGE[0] + k, NODE[0], NODE[1], act)  # φv
        self.hierarchy = HierarchyPass(d, act, dt_feature) if hierarchical else None
        self.dt_feature = bool(dt_feature)

    def forward(
        self,
        graph: ParticleEdges,
        feats: torch.Tensor,  # [P, d] particle features (no positions)
        pos: torch.Tensor,  # [P, 2] particle positions
        box_size: float,
        cell_feats: Sequence[torch.Tensor] = (),  # per level: [C_l, d] (hierarchical graphs only)
        cell_pos: Sequence[torch.Tensor] = (),  # per level: [C_l, 2] (hierarchical graphs only)
        dt: torch.Tensor | None = None,  # [1, 1] time step feature (when dt_feature)
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """([P, 100] node embeddings, [P, 150] per-particle sum of incoming edge embeddings).

        The edge sum is what a global block aggregates (HOGN): the per-sample sum over particles of the
        per-particle edge sums is the sum over all of the sample's edges, the φc→p edges included.
        """
        extra: list[tuple[torch.Tensor, None]] = []
        if self.dt_feature:
            assert dt is not None, "a block built with dt_feature needs the time step `dt`"
            extra = [(dt, None)]
        snd, rcv = graph.edge_index
        vec = graph.vectors(pos, box_size)  # [E, 2]
        incoming = self.edge.segment_sum_parts([(feats, snd), (feats, rcv), (vec, None), *extra], rcv, graph.n_nodes)
        if self.hierarchy is not None:
            if graph.hierarchy is None:
                raise ValueError("a hierarchical block needs a graph built with graph=hierarchical.")
            incoming = incoming + self.hierarchy(
                graph.hierarchy, feats, pos, cell_feats, cell_pos, dt if self.dt_feature else None
            )
        nodes = self.node.forward_parts([(feats, None), (incoming, None), *extra], graph.n_nodes)
        return nodes, incoming


def sample_sums(
    values: torch.Tensor,  # [P, F] per-particle values, P = B*N in sample-major order
    n_graphs: int,
) -> torch.Tensor:
    """[B, F] per-sample sums (a segment sum with contiguous, equal segments)."""
    return values.reshape(n_graphs, -1, values.shape[-1]).sum(dim=1)
