"""Graph-network blocks: gathered first layers, segment sums, equivariance and batch independence."""

from __future__ import annotations

import math

import pytest
import torch

from mpsim.graphs.batch import segment_sum
from mpsim.graphs.hierarchy import build_hierarchy
from mpsim.graphs.knn import full_graph, knn_graph
from mpsim.models.gn_blocks import MLP, InteractionBlock, ParticleEdges, sample_sums


def _state(b: int, n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, float]:
    """([B, N, 2] positions, [B, N, 2] velocities, [B, N] masses, box) in float64."""
    box = math.sqrt(12 * n)
    g = torch.Generator().manual_seed(seed)
    pos = (torch.rand(b, n, 2, generator=g, dtype=torch.float64) - 0.5) * box
    vel = torch.rand(b, n, 2, generator=g, dtype=torch.float64) * 2 - 1
    mass = 0.5 + torch.rand(b, n, generator=g, dtype=torch.float64)
    return pos, vel, mass, box


def _edges(kind: str, pos: torch.Tensor, mass: torch.Tensor, vel: torch.Tensor, box: float) -> ParticleEdges:
    b, n, _ = pos.shape
    if kind == "full":
        return ParticleEdges(full_graph(pos, box).edge_index, b, n)
    if kind == "knn":
        return ParticleEdges(knn_graph(pos, box, 6).edge_index, b, n)
    h = build_hierarchy(pos, box, mass=mass, vel=vel)
    return ParticleEdges(h.pp_edge_index, b, n, h)


def _run(block: InteractionBlock, kind: str, pos, vel, mass, box) -> torch.Tensor:
    """[B*N, 100] node embeddings of the block on the `kind` graph of the state."""
    graph = _edges(kind, pos, mass, vel, box)
    feats = torch.cat([mass.reshape(-1, 1), vel.reshape(-1, 2)], dim=-1)
    cells = [] if graph.hierarchy is None else graph.hierarchy.cells
    cell_feats = [torch.cat([c.mass[:, None], c.vel], dim=-1) for c in cells]
    dt = torch.full((1, 1), 0.01, dtype=torch.float64)
    nodes, _ = block(graph, feats, pos.reshape(-1, 2), box, cell_feats, [c.pos for c in cells], dt)
    return nodes


def test_forward_parts_equals_concatenated_input() -> None:
    torch.manual_seed(0)
    mlp = MLP(3 + 3 + 2 + 1, 16, 2, "relu").double()
    nodes = torch.randn(5, 3, dtype=torch.float64)
    snd, rcv = torch.tensor([0, 1, 4, 2]), torch.tensor([1, 0, 0, 3])
    vec = torch.randn(4, 2, dtype=torch.float64)
    dt = torch.full((1, 1), 0.01, dtype=torch.float64)
    dense = mlp(torch.cat([nodes[snd], nodes[rcv], vec, dt.expand(4, 1)], dim=-1))
    parts = mlp.forward_parts([(nodes, snd), (nodes, rcv), (vec, None), (dt, None)], 4)
    assert torch.allclose(dense, parts, atol=1e-12)
    with pytest.raises(ValueError, match="expects 9 input features"):
        mlp.forward_parts([(nodes, snd), (vec, None)], 4)


def test_mlp_has_activation_after_every_layer() -> None:
    mlp = MLP(4, 8, 3, "relu")
    assert len(mlp.layers) == 3
    assert (mlp(torch.randn(50, 4) * 10) >= 0).all()  # ReLU after the last layer too (reference blocks)


def test_segment_and_sample_sums() -> None:
    values = torch.arange(12.0).reshape(6, 2)
    index = torch.tensor([2, 0, 2, 2, 0, 3])
    out = segment_sum(values, index, 5)
    expected = torch.zeros(5, 2)
    for row, seg in zip(values, index, strict=True):  # the loop is the oracle, not the implementation
        expected[seg] += row
    assert torch.equal(out, expected) and (out[1] == 0).all() and (out[4] == 0).all()
    assert torch.equal(sample_sums(values, 2), values.reshape(2, 3, 2).sum(1))


@pytest.mark.parametrize("kind", ["full", "knn", "hierarchical"])
def test_block_is_permutation_equivariant(kind: str) -> None:
    torch.manual_seed(1)
    block = InteractionBlock(3, "relu", dt_feature=True, hierarchical=kind == "hierarchical").double()
    pos, vel, mass, box = _state(1, 40, seed=2)
    perm = torch.randperm(40)
    a = _run(block, kind, pos, vel, mass, box)
    b = _run(block, kind, pos[:, perm], vel[:, perm], mass[:, perm], box)
    assert torch.allclose(a[perm], b, atol=1e-10)


@pytest.mark.parametrize("kind", ["full", "knn", "hierarchical"])
def test_batched_samples_are_independent(kind: str) -> None:
    torch.manual_seed(3)
    block = InteractionBlock(3, "softplus", dt_feature=True, hierarchical=kind == "hierarchical").double()
    pos, vel, mass, box = _state(2, 30, seed=4)
    together = _run(block, kind, pos, vel, mass, box).reshape(2, 30, -1)
    for s in range(2):
        alone = _run(block, kind, pos[s : s + 1], vel[s : s + 1], mass[s : s + 1], box)
        assert torch.allclose(together[s], alone, atol=1e-10)


def test_hierarchical_block_needs_a_hierarchy() -> None:
    block = InteractionBlock(3, "relu", dt_feature=False, hierarchical=True)
    pos, vel, mass, box = _state(1, 10)
    graph = _edges("full", pos.float(), mass.float(), vel.float(), box)
    feats = torch.cat([mass.reshape(-1, 1), vel.reshape(-1, 2)], dim=-1).float()
    with pytest.raises(ValueError, match="graph=hierarchical"):
        block(graph, feats, pos.reshape(-1, 2).float(), box)
