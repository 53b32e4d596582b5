"""Quadtree hierarchy: assignments, cell sums, edge sets against brute-force definitions, scaling."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from mpsim.errors import ConfigError
from mpsim.graphs.hierarchy import Hierarchy, build_hierarchy, hierarchy_depth


def _state(b: int, n: int, seed: int, box: float | None = None) -> tuple[torch.Tensor, ...]:
    """(pos [B, N, 2], mass [B, N], vel [B, N, 2], charge [B, N], box) for uniform particles."""
    box = math.sqrt(12 * n) if box is None else box
    g = torch.Generator().manual_seed(seed)
    pos = (torch.rand(b, n, 2, generator=g, dtype=torch.float64) - 0.5) * box
    mass = 0.5 + torch.rand(b, n, generator=g, dtype=torch.float64)
    vel = torch.rand(b, n, 2, generator=g, dtype=torch.float64) * 2 - 1
    charge = torch.rand(b, n, generator=g, dtype=torch.float64) * 2 - 1
    return pos, mass, vel, charge, box


def _cell_rc(pos: np.ndarray, box: float, grid: int) -> tuple[np.ndarray, np.ndarray]:
    """(row, col) of each position on a grid x grid partition; row 0 at the top (largest y)."""
    ij = np.clip(np.floor((pos + box / 2) / (box / grid)).astype(int), 0, grid - 1)
    return grid - 1 - ij[..., 1], ij[..., 0]


def _cheb(a: np.ndarray, b: np.ndarray, grid: int) -> np.ndarray:
    """Periodic Chebyshev distance between integer grid coordinates."""
    d = np.abs(a - b) % grid
    return np.minimum(d, grid - d)


def test_depth_follows_the_reference() -> None:
    assert [hierarchy_depth(n) for n in (20, 100, 1000, 5000, 10000)] == [2, 3, 5, 6, 7]
    assert hierarchy_depth(3) == 2
    with pytest.raises(ConfigError, match="depth"):
        build_hierarchy(torch.zeros(5, 2), 4.0, depth=1)


def test_assignment_and_cell_sums() -> None:
    b, n = 3, 300
    pos, mass, vel, charge, box = _state(b, n, seed=0)
    h = build_hierarchy(pos, box, mass=mass, vel=vel, charge=charge)
    assert h.depth == hierarchy_depth(n) == 4 and [c.grid for c in h.cells] == [16, 8, 4]
    lowest = h.cells[0]
    # every particle sits in exactly one lowest cell, of its own sample, whose square contains it
    assert h.particle_cell.shape == (b * n,) and (h.particle_cell >= 0).all()
    assert torch.equal(lowest.batch[h.particle_cell], torch.arange(b).repeat_interleave(n))
    off = pos.reshape(-1, 2) - lowest.centre[h.particle_cell]
    assert (off.abs() <= lowest.cell_size / 2 + 1e-12).all()
    p_mass, p_pos, p_vel, p_q = mass.reshape(-1), pos.reshape(-1, 2), vel.reshape(-1, 2), charge.reshape(-1)
    for level in h.cells:
        # the particles of each cell, by brute force from the positions
        rows, cols = _cell_rc(pos.numpy(), box, level.grid)
        for c in np.random.default_rng(0).choice(level.n_cells, size=10, replace=False):
            s, r, q = int(level.batch[c]), int(level.row[c]), int(level.col[c])
            members = torch.from_numpy(np.nonzero((rows[s] == r) & (cols[s] == q))[0]) + s * n
            assert int(level.count[c]) == len(members) > 0  # no empty cells
            m = p_mass[members]
            assert torch.isclose(level.mass[c], m.sum(), rtol=1e-12)
            # total charge, not the mean (spec §7.2)
            assert torch.isclose(level.charge[c], p_q[members].sum(), rtol=1e-12, atol=1e-12)
            assert torch.allclose(level.pos[c], (m[:, None] * p_pos[members]).sum(0) / m.sum(), rtol=1e-10)
            assert torch.allclose(level.vel[c], (m[:, None] * p_vel[members]).sum(0) / m.sum(), rtol=1e-10)
        # cell sums equal particle sums per sample; non-empty cells = occupied squares
        per_sample = torch.zeros(b, dtype=torch.float64).index_add(0, level.batch, level.mass)
        assert torch.allclose(per_sample, mass.sum(1))
        assert int(level.count.sum()) == b * n
        occupied = sum(len(set(zip(rows[s].tolist(), cols[s].tolist(), strict=True))) for s in range(b))
        assert level.n_cells == occupied
        assert level.features().shape == (level.n_cells, 6)


def test_parent_assignment() -> None:
    pos, mass, vel, _, box = _state(2, 500, seed=1)
    h = build_hierarchy(pos, box, mass=mass, vel=vel)
    for child, parent in itertools.pairwise(h.cells):
        up = child.assignment()
        assert up.shape == (2, child.n_cells)
        p = child.parent
        assert torch.equal(parent.row[p], child.row // 2) and torch.equal(parent.col[p], child.col // 2)
        assert torch.equal(parent.batch[p], child.batch)
        assert torch.equal(torch.zeros_like(parent.count).index_add(0, p, child.count), parent.count)
        assert len(torch.unique(p)) == parent.n_cells  # every parent has a child
    assert h.cells[-1].parent is None and h.cells[-1].charge is None
    assert h.cells[-1].features().shape[1] == 5


def _check_edges(h: Hierarchy, pos: torch.Tensor, box: float) -> None:
    """pp and near-neighbour edge sets equal the brute-force definitions (spec §2)."""
    b, n, _ = pos.shape
    lowest = h.cells[0]
    rows, cols = _cell_rc(pos.numpy(), box, lowest.grid)
    rows, cols = rows.reshape(-1), cols.reshape(-1)
    sample = np.repeat(np.arange(b), n)
    # particle-particle: same sample, different particle, lowest cells within the periodic 3x3 block
    close = (
        (sample[:, None] == sample[None, :])
        & (_cheb(rows[:, None], rows[None, :], lowest.grid) <= 1)
        & (_cheb(cols[:, None], cols[None, :], lowest.grid) <= 1)
    )
    np.fill_diagonal(close, False)
    recv, send = np.nonzero(close)
    expected = set(zip(send.tolist(), recv.tolist(), strict=True))
    got = list(zip(*h.pp_edge_index.tolist(), strict=True))
    assert len(got) == len(set(got)) and set(got) == expected
    assert (np.diff(h.pp_edge_index[1].numpy()) >= 0).all()  # sorted by receiver
    # near-neighbour cell edges: parents adjacent (or equal), cells not adjacent (nor equal)
    for level in h.cells:
        r, c, s = level.row.numpy(), level.col.numpy(), level.batch.numpy()
        half = level.grid // 2
        parents_adjacent = (_cheb(r[:, None] // 2, r[None, :] // 2, half) <= 1) & (
            _cheb(c[:, None] // 2, c[None, :] // 2, half) <= 1
        )
        adjacent = _cheb(r[:, None], r[None, :], level.grid) <= 1
        adjacent &= _cheb(c[:, None], c[None, :], level.grid) <= 1
        near = (s[:, None] == s[None, :]) & parents_adjacent & ~adjacent
        recv, send = np.nonzero(near)
        got = list(zip(*level.edge_index.tolist(), strict=True))
        assert len(got) == len(set(got))
        assert set(got) == set(zip(send.tolist(), recv.tolist(), strict=True))
        per_receiver = np.bincount(level.edge_index[1].numpy(), minlength=level.n_cells)
        assert per_receiver.max() <= (7 if level.grid == 4 else 27)


@pytest.mark.parametrize("n", [40, 300])
def test_edges_match_definition(n: int) -> None:
    pos, mass, vel, _, box = _state(2, n, seed=2)
    h = build_hierarchy(pos, box, mass=mass, vel=vel)
    _check_edges(h, pos, box)


def test_edges_with_empty_cells_and_clusters() -> None:
    """Clustered particles leave most cells empty: no edge may touch a pruned cell."""
    g = torch.Generator().manual_seed(5)
    box = 40.0
    pos = torch.randn(2, 200, 2, generator=g, dtype=torch.float64) * 3.0 + 18.0  # straddles the box corner
    h = build_hierarchy(pos, box, depth=4)
    _check_edges(h, ((pos + box / 2) % box) - box / 2, box)
    for level in h.cells:
        assert (level.count > 0).all()
        assert int(level.edge_index.max()) < level.n_cells


def test_full_grid_has_27_near_neighbours() -> None:
    """One particle at every lowest cell centre: 27 near neighbours per cell, 7 on the 4x4 top."""
    grid, box = 16, 32.0
    centres = (torch.arange(grid, dtype=torch.float64) + 0.5) * (box / grid) - box / 2
    pos = torch.cartesian_prod(centres, centres)[None]  # [1, 256, 2]
    h = build_hierarchy(pos, box, depth=4)
    assert torch.equal(h.cells[0].count, torch.ones(256, dtype=torch.long))
    for level in h.cells:
        per_receiver = torch.bincount(level.edge_index[1], minlength=level.n_cells)
        assert (per_receiver == (7 if level.grid == 4 else 27)).all()
    assert h.n_edges()["particle_particle"] == 256 * 8


def test_batch_equals_separate_builds() -> None:
    pos, mass, vel, charge, box = _state(3, 120, seed=3)
    together = build_hierarchy(pos, box, mass=mass, vel=vel, charge=charge)
    n = 120
    cell_offsets = [0] * len(together.cells)
    for s in range(3):
        alone = build_hierarchy(pos[s], box, mass=mass[s], vel=vel[s], charge=charge[s])
        sl = slice(s * n, (s + 1) * n)
        assert torch.equal(together.particle_cell[sl] - cell_offsets[0], alone.particle_cell)
        pp = together.pp_edge_index
        mine = pp[:, (pp[1] >= s * n) & (pp[1] < (s + 1) * n)] - s * n
        assert torch.equal(mine, alone.pp_edge_index)
        for li, (lt, la) in enumerate(zip(together.cells, alone.cells, strict=True)):
            cells = lt.batch == s
            assert torch.allclose(lt.features()[cells], la.features())
            e = lt.edge_index[:, cells[lt.edge_index[1]]] - cell_offsets[li]
            assert torch.equal(e, la.edge_index)
            cell_offsets[li] += la.n_cells


def test_edges_per_particle_roughly_constant() -> None:
    """O(N) graph: particle-particle edges follow 9 (N - 1) / 4^depth; all edges per particle stay flat."""
    totals = {}
    for n in (100, 1000, 10000):
        pos, _, _, _, box = _state(1, n, seed=4)
        counts = build_hierarchy(pos, box).n_edges()
        depth = hierarchy_depth(n)
        assert counts["particle_particle"] / n == pytest.approx(9 * (n - 1) / 4**depth, rel=0.15)
        totals[n] = (counts["particle_particle"] + counts["cell_cell"] + counts["assignment"]) / n
        assert counts["cells"] < 2 * n  # Theorem 1: fewer cells than 2N
    assert max(totals.values()) / min(totals.values()) < 2.0, totals
    assert max(totals.values()) < 40  # against N - 1 = 9999 for the full graph


def test_with_features_is_differentiable_and_consistent() -> None:
    pos, mass, vel, charge, box = _state(2, 100, seed=6)
    h = build_hierarchy(pos, box, mass=mass, vel=vel, charge=charge)
    p = pos.clone().requires_grad_(True)
    again = h.with_features(mass, p, vel, charge)
    for a, b in zip(h.cells, again.cells, strict=True):
        assert torch.allclose(a.features(), b.features().detach(), rtol=1e-12, atol=1e-12)
    # d(Σ over top cells of M X)/d x_i = m_i: centres of mass are linear in the particle positions
    top = again.cells[-1]
    (grad,) = torch.autograd.grad((top.mass[:, None] * top.pos).sum(), p)
    assert torch.allclose(grad, mass[..., None].expand(-1, -1, 2), rtol=1e-12)


def test_deterministic_and_default_features() -> None:
    pos, _, _, _, box = _state(1, 64, seed=7)
    a, b = build_hierarchy(pos, box), build_hierarchy(pos[0], box)
    assert torch.equal(a.pp_edge_index, b.pp_edge_index)
    assert torch.equal(a.cells[0].mass, a.cells[0].count.to(torch.float64))  # default unit masses
    assert torch.equal(a.cells[0].vel, torch.zeros_like(a.cells[0].vel))
