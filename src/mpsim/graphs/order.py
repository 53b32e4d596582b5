"""Z-order (Morton) keys of grid cells and the space-filling-curve order of particles, for memory locality.

A graph network's gathers (x_sender for every edge) and segment sums (Σ over the edges into a receiver, over
the members of a cell) touch memory in the order of the node ids. With particles in random order, the senders of
one receiver and the members of one cell are scattered through [P, 150]-wide tables, and each gather misses the
cache once the tables outgrow it (N ≳ 10^4). Numbering particles, and cells, along the Z-order curve puts
spatial neighbours next to each other in memory: the quadtree's cells are Z-order prefixes, so the particles of a
cell, the children of a parent and the 3x3 block around a cell are (nearly) contiguous.

The grid is the quadtree's (`hierarchy.build_hierarchy`): the periodic box [-L/2, L/2)^2 split into
`grid` x `grid` cells, row 0 at the top (largest y), column 0 at the left.
"""

from __future__ import annotations

import torch

from mpsim.periodic import wrap_positions

# (shift, mask) steps that spread the low 32 bits of an int64 onto its even bits, and that pack them back.
_SPREAD = (
    (16, 0x0000FFFF0000FFFF),
    (8, 0x00FF00FF00FF00FF),
    (4, 0x0F0F0F0F0F0F0F0F),
    (2, 0x3333333333333333),
    (1, 0x5555555555555555),
)
_PACK = (
    (1, 0x3333333333333333),
    (2, 0x0F0F0F0F0F0F0F0F),
    (4, 0x00FF00FF00FF00FF),
    (8, 0x0000FFFF0000FFFF),
    (16, 0x00000000FFFFFFFF),
)


def _spread(v: torch.Tensor) -> torch.Tensor:  # v: [...] int64 in [0, 2^31)
    """[...] the bits of `v` moved to the even bit positions (bit k -> bit 2k)."""
    for shift, mask in _SPREAD:
        v = (v | (v << shift)) & mask
    return v


def _pack(v: torch.Tensor) -> torch.Tensor:  # v: [...] non-negative int64
    """[...] the even bits of `v` packed together (bit 2k -> bit k; the inverse of `_spread`)."""
    v = v & 0x5555555555555555
    for shift, mask in _PACK:
        v = (v | (v >> shift)) & mask
    return v


def morton_encode(
    row: torch.Tensor,  # [...] int64 cell rows, 0 <= row < 2^31
    col: torch.Tensor,  # [...] int64 cell columns, 0 <= col < 2^31
) -> torch.Tensor:
    """[...] Z-order key: the bits of row and column interleaved (row bits odd, column bits even).

    On a 2^l grid the keys run over 0 .. 4^l - 1, and key >> 2 is the key of the parent cell on the 2^(l-1) grid,
    so the four children of a cell have consecutive keys.
    """
    return (_spread(row) << 1) | _spread(col)


def morton_decode(code: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:  # code: [...] int64 Z-order keys
    """([...] row, [...] column) of each Z-order key (the inverse of `morton_encode`)."""
    return _pack(code >> 1), _pack(code)


def grid_cells(
    pos: torch.Tensor,  # [..., 2] positions (any real values: wrapped into the box first)
    box_size: float,
    grid: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """([...] row, [...] column) of the cell of each position on the grid x grid partition of the periodic box."""
    ij = torch.floor((wrap_positions(pos.detach(), box_size) + box_size / 2) / (box_size / grid)).long()
    ij = ij.clamp_(0, grid - 1)  # (column from x, row-from-the-bottom from y)
    return grid - 1 - ij[..., 1], ij[..., 0]


def spatial_order(
    pos: torch.Tensor,  # [B, N, 2] particle positions
    box_size: float,
    depth: int,
) -> torch.Tensor:
    """[B*N] flattened particle ids b*N + i sorted by (sample, Z-order key of their cell on the 2^depth grid).

    Each sample's particles stay in that sample's block of N slots (position b*N + j holds a particle of sample
    b), so the result is a permutation within samples. Particles of one cell keep their input order (a stable
    sort), so the order is deterministic. With `depth` the quadtree's depth, a hierarchy built from the
    reordered particles has non-decreasing particle -> cell ids.
    """
    b, n, _ = pos.shape
    grid = 1 << depth
    row, col = grid_cells(pos, box_size, grid)  # [B, N] each
    sample = torch.arange(b, device=pos.device)[:, None]  # [B, 1]
    key = (sample * (grid * grid) + morton_encode(row, col)).reshape(-1)  # [B*N]
    return torch.argsort(key, stable=True)
