"""The quadtree hierarchy of Martinkus et al. (AAAI 2021) for particles in a periodic square box.

The box [-L/2, L/2)^2 is split `depth` = round(log4 N) times, so the lowest cell grid is 2^depth per side
and holds about one particle per cell for uniform data. Cell levels run from that grid up to the 4x4
grid; the 2x2 level is dropped (its 4 cells are all neighbours, so it would carry no interaction). The
graph has:

1. particle-particle edges at the lowest level: every particle of a cell's periodic 3x3 block sends to
   every particle of the cell (self-loops excluded; each unordered pair appears in both directions);
2. near-neighbour cell-cell edges at every cell level: the children of the parent's periodic 3x3 block
   minus the cell's own 3x3 block, i.e. 36 - 9 = 27 senders per receiver, and 16 - 9 = 7 on the 4x4 grid,
   whose parent grid (2x2) wraps onto itself;
3. assignments: particle -> lowest cell and child cell -> parent cell (used upward, and reversed downward).

Empty cells are pruned: cell ids are compact per level, over the whole batch, ordered by sample and then
along the Z-order (Morton) curve of (row, column), row 0 at the top (largest y) and column 0 at the left
(`graphs.order`; the reference builder numbers cells row by row). In Z-order the four children of a parent have
consecutive ids, so the child -> parent ids are non-decreasing and a cell's 3x3 block lies close by in memory;
particles numbered in the same order (`order.spatial_order`, as the N-body models do before building the graph)
get non-decreasing particle -> cell ids. Cell features are Σ mass, Σ charge (the *total*, as the paper states; the reference's rollout builder used a
mean, spec §7.2), centre of mass and mass-weighted mean velocity.

Everything is vectorised: cell ids come from floor division, neighbour cells from offsets modulo the grid,
and the particle lists from one sort plus segment sums. A level's dense cell key is
sample * grid² + Z-order key, and the parent's is sample * (grid/2)² + (Z-order key >> 2). The only Python loop is over the ~log4 N levels.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from itertools import product
from typing import Any

import torch

from mpsim.errors import ConfigError
from mpsim.graphs.batch import segment_sum
from mpsim.graphs.order import grid_cells, morton_decode, morton_encode
from mpsim.periodic import minimum_image, wrap_positions


def hierarchy_depth(n_particles: int) -> int:
    """round(log4 N), at least 2: the number of splits, so the lowest grid has about N cells."""
    return max(2, int(round(math.log(max(n_particles, 1)) / math.log(4))))


# Offsets (d_row, d_col) of a cell's periodic 3x3 block.
_BLOCK = torch.tensor(list(product((-1, 0, 1), repeat=2)), dtype=torch.long)  # [9, 2]


def _near_offsets() -> torch.Tensor:
    """[4, 27, 2] near-neighbour offsets for each (row parity, column parity) on grids of side >= 8.

    A cell at row r has parent row r // 2; the children of the parent rows r//2 - 1 .. r//2 + 1 are the
    rows r - 2 - p .. r + 3 - p with p = r mod 2 (six rows). Near neighbours are the 6x6 children of the
    parent's 3x3 block minus the cell's own 3x3 block.
    """
    tables = []
    for pr, pc in product((0, 1), repeat=2):
        tables.append(
            [
                (dr, dc)
                for dr in range(-2 - pr, 4 - pr)
                for dc in range(-2 - pc, 4 - pc)
                if not (abs(dr) <= 1 and abs(dc) <= 1)
            ]
        )
    return torch.tensor(tables, dtype=torch.long)


_NEAR = _near_offsets()  # [4, 27, 2]
# On the 4x4 grid the parent 3x3 block wraps over the whole 2x2 parent grid: all 16 cells minus own 3x3.
_NEAR_4X4 = torch.tensor(
    [(dr, dc) for dr in range(-1, 3) for dc in range(-1, 3) if not (abs(dr) <= 1 and abs(dc) <= 1)],
    dtype=torch.long,
)  # [7, 2]


@dataclass(frozen=True)
class CellLevel:
    """The non-empty cells of one level, for all samples of the batch (C cells in all).

    Attributes:
        grid: cells per box side at this level (2^l).
        cell_size: side of one cell, L / grid.
        batch: [C] sample index of each cell.
        row: [C] grid row (0 = top, largest y).
        col: [C] grid column (0 = left, smallest x).
        centre: [C, 2] geometric centre of each cell.
        count: [C] number of particles in each cell (always >= 1: empty cells are pruned).
        mass: [C] total mass.
        charge: [C] total charge, or None when no charges were given (gravity).
        pos: [C, 2] centre of mass (inside the cell).
        vel: [C, 2] mass-weighted mean velocity.
        edge_index: [2, E_c] near-neighbour (sender, receiver) cell ids at this level, sorted by receiver.
        parent: [C] id of each cell's parent in the next level up; None at the top (4x4) level.
    """

    grid: int
    cell_size: float
    batch: torch.Tensor
    row: torch.Tensor
    col: torch.Tensor
    centre: torch.Tensor
    count: torch.Tensor
    mass: torch.Tensor
    charge: torch.Tensor | None
    pos: torch.Tensor
    vel: torch.Tensor
    edge_index: torch.Tensor
    parent: torch.Tensor | None

    @property
    def n_cells(self) -> int:
        return int(self.batch.shape[0])

    def features(self) -> torch.Tensor:
        """[C, 5] (Σm, X, Y, VX, VY), or [C, 6] (Σm, Σq, X, Y, VX, VY) with charges (the reference order)."""
        cols = [self.mass[:, None]] + ([] if self.charge is None else [self.charge[:, None]])
        return torch.cat(cols + [self.pos, self.vel], dim=-1)

    def assignment(self) -> torch.Tensor:
        """[2, C] (child, parent) pairs, child ids 0..C-1 in order (reverse the rows for parent -> child)."""
        if self.parent is None:
            raise ValueError("the top (4x4) level has no parent level.")
        return torch.stack([torch.arange(self.n_cells, device=self.parent.device), self.parent])


@dataclass(frozen=True)
class Hierarchy:
    """The hierarchical graph of B samples of N particles each (particle i of sample b is node b*N + i).

    Attributes:
        box_size: side L of the periodic box.
        n_graphs: B samples.
        n_particles: N particles per sample.
        particle_cell: [B*N] id of each particle's lowest-level cell in `cells[0]` (its assignment).
        pp_edge_index: [2, E_pp] particle-particle (sender, receiver) edges within lowest-level 3x3 blocks,
            sorted by receiver.
        cells: the cell levels, lowest (2^depth per side) first, top (4x4) last.
    """

    box_size: float
    n_graphs: int
    n_particles: int
    particle_cell: torch.Tensor
    pp_edge_index: torch.Tensor
    cells: list[CellLevel]

    @property
    def depth(self) -> int:
        """round(log4 N): the number of quadtree splits (cell levels + the dropped 2x2 level)."""
        return len(self.cells) + 1

    def particle_assignment(self) -> torch.Tensor:
        """[2, B*N] (particle, lowest cell) pairs (reverse the rows for cell -> particle)."""
        idx = torch.arange(self.particle_cell.shape[0], device=self.particle_cell.device)
        return torch.stack([idx, self.particle_cell])

    def n_edges(self) -> dict[str, int]:
        """Edge counts: particle-particle, cell-cell (all levels), assignments (one direction), cells."""
        return {
            "particle_particle": int(self.pp_edge_index.shape[1]),
            "cell_cell": sum(int(c.edge_index.shape[1]) for c in self.cells),
            "assignment": int(self.particle_cell.shape[0]) + sum(c.n_cells for c in self.cells[:-1]),
            "cells": sum(c.n_cells for c in self.cells),
        }

    def with_features(
        self,
        mass: torch.Tensor,  # [B, N] or [B*N] particle masses
        pos: torch.Tensor,  # [B, N, 2] or [B*N, 2] particle positions
        vel: torch.Tensor,  # [B, N, 2] or [B*N, 2] particle velocities
        charge: torch.Tensor | None = None,  # [B, N] or [B*N] particle charges
    ) -> Hierarchy:
        """The same graph with cell features recomputed from new particle values (fixed assignment).

        Differentiable in the particle values, so a Hamiltonian model can rebuild cell features inside each
        integrator stage. Centres of mass are measured from the fixed cell centres with the minimum image,
        so a particle that has drifted slightly out of its cell (or across the box face) still counts at its
        nearest periodic position.
        """
        parents = []
        for c in self.cells[:-1]:
            assert c.parent is not None  # every level below the top has one
            parents.append(c.parent)
        feats = cell_features(
            self.particle_cell,
            parents,
            [c.centre for c in self.cells],
            self.box_size,
            mass.reshape(-1),
            pos.reshape(-1, 2),
            vel.reshape(-1, 2),
            None if charge is None else charge.reshape(-1),
        )
        cells = []
        for c, (m, q, x, v) in zip(self.cells, feats, strict=True):
            cells.append(replace(c, mass=m, charge=q, pos=x, vel=v))
        return replace(self, cells=cells)


def cell_features(
    particle_cell: torch.Tensor,  # [P] lowest-level cell of each particle
    parents: Sequence[torch.Tensor],  # per level below the top: [C_l] parent id of each cell
    centres: Sequence[torch.Tensor],  # per level: [C_l, 2] geometric cell centres
    box_size: float,
    mass: torch.Tensor,  # [P] particle masses
    pos: torch.Tensor,  # [P, 2] particle positions
    vel: torch.Tensor,  # [P, 2] particle velocities
    charge: torch.Tensor | None = None,  # [P] particle charges
) -> list[tuple[torch.Tensor, torch.Tensor | None, torch.Tensor, torch.Tensor]]:
    """Per level, lowest first: (Σm [C], Σq [C] or None, centre of mass [C, 2], mean velocity [C, 2]).

    The velocity is the mass-weighted mean. Upper levels are aggregated from their children's sums, so every
    level's centre of mass and velocity are exact particle averages. A cell of zero total mass gets its
    geometric centre and zero velocity.
    """
    out = []
    index, m, q, x, v = particle_cell, mass, charge, pos, vel
    for level, centre in enumerate(centres):
        n = centre.shape[0]
        m_sum = segment_sum(m, index, n)
        # offsets from the cell centre by minimum image: robust to unwrapped or stage-perturbed positions
        dx = minimum_image(x - centre[index], box_size)
        mx = segment_sum(m[:, None] * dx, index, n)
        mv = segment_sum(m[:, None] * v, index, n)
        denom = torch.where(m_sum != 0, m_sum, torch.ones_like(m_sum))[:, None]
        com = wrap_positions(centre + mx / denom, box_size)
        q_sum = None if q is None else segment_sum(q, index, n)
        out.append((m_sum, q_sum, com, mv / denom))
        if level < len(parents):
            index, m, q, x, v = parents[level], m_sum, q_sum, com, mv / denom
    return out


def build_hierarchy(
    pos: torch.Tensor,  # [B, N, 2] or [N, 2] particle positions
    box_size: float,
    mass: torch.Tensor | None = None,  # [B, N] or [N] particle masses (default 1)
    vel: torch.Tensor | None = None,  # [B, N, 2] or [N, 2] particle velocities (default 0)
    charge: torch.Tensor | None = None,  # [B, N] or [N] particle charges (None: no charge feature)
    depth: int | None = None,
) -> Hierarchy:
    """Build the quadtree hierarchy of a batch of particle states.

    Args:
        pos: [B, N, 2] (or [N, 2]) positions; wrapped into [-L/2, L/2) before binning.
        box_size: side L of the periodic box.
        mass: [B, N] masses; default ones.
        vel: [B, N, 2] velocities; default zeros.
        charge: [B, N] charges, or None for gravity (cells then carry no charge feature).
        depth: number of splits (the paper's L, reference `levels`); default round(log4 N), at least 2.

    Returns:
        A `Hierarchy` with all ids flattened over the batch.

    Raises:
        ConfigError: if `depth` < 2 (the 4x4 grid is the coarsest level kept).
    """
    pos3 = pos[None] if pos.dim() == 2 else pos
    b, n, _ = pos3.shape
    depth = hierarchy_depth(n) if depth is None else int(depth)
    if depth < 2:
        raise ConfigError(f"hierarchy depth must be >= 2 (the 4x4 grid is the top level kept); got {depth}.")
    dev = pos3.device
    dtype = pos3.dtype  # features follow the positions' precision (float64 data, float32 models)
    mass = torch.ones(b, n, dtype=dtype, device=dev) if mass is None else mass.to(dtype).expand(b, n)
    vel = torch.zeros_like(pos3) if vel is None else vel.to(dtype).expand(b, n, 2)
    charge = None if charge is None else charge.to(dtype).expand(b, n)

    # lowest-level integer cell coordinates; binning never needs gradients
    grid = 1 << depth
    row, col = (rc.reshape(-1) for rc in grid_cells(pos3, box_size, grid))  # [B*N] each
    sample = torch.arange(b, device=dev).repeat_interleave(n)  # [B*N]

    # lowest level: particles -> cells, and the particle-particle edges
    key = sample * (grid * grid) + morton_encode(row, col)  # [B*N] dense cell key
    counts = torch.bincount(key, minlength=b * grid * grid)
    dense, occupied = _compact(counts)
    particle_cell = dense[key]
    pp_edges = _particle_edges(key, counts, sample, row, col, grid)

    levels = _cell_levels(occupied, dense, counts, b, grid, box_size, dtype)
    feats = cell_features(
        particle_cell,
        [lv["parent"] for lv in levels[:-1]],
        [lv["centre"] for lv in levels],
        box_size,
        mass.reshape(-1),
        pos3.reshape(-1, 2),
        vel.reshape(-1, 2),
        None if charge is None else charge.reshape(-1),
    )
    cells = []
    for lv, (m, q, x, v) in zip(levels, feats, strict=True):
        cells.append(CellLevel(**lv, mass=m, charge=q, pos=x, vel=v))
    return Hierarchy(
        box_size=float(box_size),
        n_graphs=b,
        n_particles=n,
        particle_cell=particle_cell,
        pp_edge_index=pp_edges,
        cells=cells,
    )


def _cell_levels(
    occupied: torch.Tensor,  # [C] occupied dense keys of the lowest level, in order
    dense: torch.Tensor,  # [B*G*G] compact id of each dense key, -1 if empty
    counts: torch.Tensor,  # [B*G*G] particles per dense key
    n_graphs: int,
    grid: int,
    box_size: float,
    dtype: torch.dtype,
) -> list[dict[str, Any]]:
    """`CellLevel` fields but the features, per level: lowest (`grid` per side) first, up to the 4x4 grid."""
    b, cell_size = n_graphs, box_size / grid
    levels: list[dict[str, Any]] = []
    while True:
        c_sample, c_code = occupied // (grid * grid), occupied % (grid * grid)
        c_row, c_col = morton_decode(c_code)
        centre = torch.stack(
            [(c_col.to(dtype) + 0.5) * cell_size, -(c_row.to(dtype) + 0.5) * cell_size], dim=-1
        ) + torch.tensor([-box_size / 2, box_size / 2], dtype=dtype, device=occupied.device)
        level: dict[str, Any] = dict(
            grid=grid,
            cell_size=cell_size,
            batch=c_sample,
            row=c_row,
            col=c_col,
            centre=centre,
            count=counts[occupied],
            edge_index=_near_edges(c_sample, c_row, c_col, dense, grid),
            parent=None,
        )
        levels.append(level)
        if grid == 4:  # the 2x2 level above is dropped
            return levels
        # next level up: a child's parent is (row // 2, col // 2), Z-order key >> 2; the occupied parents are
        # those of occupied children
        grid //= 2
        cell_size *= 2
        parent_key = c_sample * (grid * grid) + (c_code >> 2)
        child_counts = torch.bincount(parent_key, minlength=b * grid * grid)
        dense, occupied = _compact(child_counts)
        level["parent"] = dense[parent_key]
        # particles per parent cell (the bincount above counts children)
        counts = segment_sum(level["count"], parent_key, child_counts.shape[0])


def _compact(counts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:  # counts: [K] per dense key
    """([K] compact id of each dense key or -1 if empty, [C] the occupied dense keys in order)."""
    occupied_mask = counts > 0
    dense = torch.cumsum(occupied_mask, 0) - 1
    dense = torch.where(occupied_mask, dense, torch.full_like(dense, -1))
    return dense, torch.nonzero(occupied_mask).squeeze(1)


def _particle_edges(
    key: torch.Tensor,  # [P] dense lowest-level cell key of each particle
    counts: torch.Tensor,  # [B*G*G] particles per dense key
    sample: torch.Tensor,  # [P] sample of each particle
    row: torch.Tensor,  # [P] cell row
    col: torch.Tensor,  # [P] cell column
    grid: int,
) -> torch.Tensor:
    """[2, E] (sender, receiver): every particle of the receiver's periodic 3x3 cell block but itself."""
    order = torch.argsort(key, stable=True)  # particles grouped by cell (a CSR layout)
    start = torch.cumsum(counts, 0) - counts  # [K] first slot of each cell in `order`
    block = _BLOCK.to(key.device)
    n_row = (row[:, None] + block[:, 0]) % grid  # [P, 9]
    n_col = (col[:, None] + block[:, 1]) % grid
    # [P*9] dense keys of the 9 cells each receiver hears
    nkey = (sample[:, None] * (grid * grid) + morton_encode(n_row, n_col)).reshape(-1)
    per_pair = counts[nkey]
    n_edges = int(per_pair.sum())
    pairs = torch.arange(nkey.shape[0], device=key.device)
    # [E] the (receiver, neighbour cell) pair each edge comes from, then its rank within that cell
    pair = torch.repeat_interleave(pairs, per_pair, output_size=n_edges)
    rank = torch.arange(n_edges, device=key.device) - (torch.cumsum(per_pair, 0) - per_pair)[pair]
    sender = order[start[nkey[pair]] + rank]
    receiver = pair // 9
    keep = sender != receiver
    return torch.stack([sender[keep], receiver[keep]])


def _near_edges(
    sample: torch.Tensor,  # [C] sample of each occupied cell
    row: torch.Tensor,  # [C] cell row
    col: torch.Tensor,  # [C] cell column
    dense: torch.Tensor,  # [B*G*G] compact id of each dense key, -1 if empty
    grid: int,
) -> torch.Tensor:
    """[2, E] (sender, receiver) near-neighbour edges between occupied cells of one level."""
    if grid == 4:
        offsets = _NEAR_4X4.to(row.device)[None].expand(row.shape[0], -1, -1)  # [C, 7, 2]
    else:
        offsets = _NEAR.to(row.device)[(row % 2) * 2 + col % 2]  # [C, 27, 2]
    s_row = (row[:, None] + offsets[..., 0]) % grid
    s_col = (col[:, None] + offsets[..., 1]) % grid
    sender = dense[sample[:, None] * (grid * grid) + morton_encode(s_row, s_col)]  # -1 for empty cells (pruned)
    receiver = torch.arange(row.shape[0], device=row.device)[:, None].expand_as(sender)
    keep = sender >= 0
    return torch.stack([sender[keep], receiver[keep]])
