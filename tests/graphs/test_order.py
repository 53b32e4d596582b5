"""Z-order keys and the space-filling-curve order of particles and quadtree cells."""

from __future__ import annotations

import math

import torch

from mpsim.graphs.hierarchy import build_hierarchy, hierarchy_depth
from mpsim.graphs.order import grid_cells, morton_decode, morton_encode, spatial_order


def test_morton_keys_round_trip_and_nest() -> None:
    g = torch.Generator().manual_seed(0)
    row, col = torch.randint(0, 2**30, (1000,), generator=g), torch.randint(0, 2**30, (1000,), generator=g)
    back = morton_decode(morton_encode(row, col))
    assert torch.equal(back[0], row) and torch.equal(back[1], col)
    rows, cols = torch.meshgrid(torch.arange(16), torch.arange(16), indexing="ij")
    key = morton_encode(rows, cols)
    assert torch.equal(key.flatten().sort().values, torch.arange(256))  # a numbering of the 16x16 grid
    assert torch.equal(morton_encode(rows // 2, cols // 2), key >> 2)  # parent = key >> 2: children consecutive
    assert morton_encode(torch.tensor([0, 0, 1, 1]), torch.tensor([0, 1, 0, 1])).tolist() == [0, 1, 2, 3]


def test_spatial_order_is_a_permutation_within_samples_along_the_curve() -> None:
    b, n, depth = 3, 500, 4
    box = math.sqrt(12 * n)
    pos = (torch.rand(b, n, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64) - 0.5) * box
    order = spatial_order(pos, box, depth)
    assert torch.equal(order.sort().values, torch.arange(b * n))
    assert torch.equal(order // n, torch.arange(b).repeat_interleave(n))  # slot b*N + j holds a particle of b
    row, col = grid_cells(pos.reshape(-1, 2)[order], box, 1 << depth)
    key = morton_encode(row, col) + (order // n) * 4**depth
    assert bool((key[1:] >= key[:-1]).all())
    same_cell = key[1:] == key[:-1]
    assert bool((order[1:][same_cell] > order[:-1][same_cell]).all())  # stable: input order within a cell


def test_hierarchy_of_ordered_particles_has_contiguous_segments() -> None:
    """Cells are numbered along the Z-order curve, so particle -> cell and child -> parent ids are sorted
    once the particles are in spatial order."""
    b, n = 2, 2000
    box = math.sqrt(12 * n)
    pos = (torch.rand(b, n, 2, generator=torch.Generator().manual_seed(2), dtype=torch.float64) - 0.5) * box
    h = build_hierarchy(pos.reshape(-1, 2)[spatial_order(pos, box, hierarchy_depth(n))].reshape(b, n, 2), box)
    assert bool((h.particle_cell[1:] >= h.particle_cell[:-1]).all())
    for level in h.cells:
        key = level.batch * level.grid**2 + morton_encode(level.row, level.col)
        assert bool((key[1:] > key[:-1]).all())  # (sample, Z-order) order
        if level.parent is not None:
            assert bool((level.parent[1:] >= level.parent[:-1]).all())
        assert bool((level.edge_index[1][1:] >= level.edge_index[1][:-1]).all())  # sorted by receiver
