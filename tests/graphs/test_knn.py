"""Periodic kNN and full graphs against brute-force minimum-image distances."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import mpsim.graphs.knn as knn_module
from mpsim.graphs.batch import sum_aggregate
from mpsim.graphs.knn import full_graph, knn_graph
from mpsim.periodic import minimum_image, wrap_positions

BOX = 10.0


def _brute_distances(pos: np.ndarray, box: float) -> np.ndarray:  # pos: [N, 2]
    """[N, N] distance to the nearest of the 9 periodic images (self = inf)."""
    n = pos.shape[0]
    best = np.full((n, n), np.inf)
    for a in (-1, 0, 1):
        for b in (-1, 0, 1):
            d = pos[None, :, :] + box * np.array([a, b]) - pos[:, None, :]
            best = np.minimum(best, np.linalg.norm(d, axis=-1))
    np.fill_diagonal(best, np.inf)
    return best


def _positions(b: int, n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(b, n, 2, generator=g, dtype=torch.float64) - 0.5) * BOX


@pytest.mark.parametrize("method", ["torch", "kdtree"])
def test_knn_matches_brute_force(method: str) -> None:
    b, n, k = 3, 150, 15
    pos = _positions(b, n, seed=0)
    graph = knn_graph(pos, BOX, k=k, method=method)
    assert graph.edge_index.shape == (2, b * n * k) and graph.edge_vec.shape == (b * n * k, 2)
    src, dst = graph.edge_index
    # receiver-major blocks of k, ids offset by sample
    assert torch.equal(dst, torch.arange(b * n).repeat_interleave(k))
    assert torch.equal(src // n, dst // n) and not (src == dst).any()
    for s in range(b):
        dist = _brute_distances(pos[s].numpy(), BOX)
        expected = np.sort(dist, axis=1)[:, :k]  # the k smallest minimum-image distances per receiver
        got_idx = (src[s * n * k : (s + 1) * n * k] - s * n).reshape(n, k).numpy()
        got = np.take_along_axis(dist, got_idx, axis=1)
        np.testing.assert_allclose(np.sort(got, axis=1), expected, rtol=1e-12)
        vec = graph.edge_vec[s * n * k : (s + 1) * n * k].reshape(n, k, 2).norm(dim=-1).numpy()
        np.testing.assert_allclose(vec, got, rtol=1e-12)


def test_knn_methods_agree_and_cross_the_box_face() -> None:
    pos = torch.tensor([[[-4.95, 0.0], [4.95, 0.0], [0.0, 0.0], [2.0, 3.0]]], dtype=torch.float64)
    for method in ("torch", "kdtree"):
        g = knn_graph(pos, BOX, k=1, method=method)
        assert g.edge_index[0].tolist() == [1, 0, 3, 2]
        # particle 1 at x = 4.95 is seen from particle 0 through the face, at -5.05
        assert torch.allclose(g.edge_vec[0], torch.tensor([-0.1, 0.0], dtype=torch.float64))
    big = _positions(2, 300, seed=1)
    a, b = knn_graph(big, BOX, method="torch"), knn_graph(big, BOX, method="kdtree")
    assert torch.allclose(a.edge_vec.norm(dim=-1), b.edge_vec.norm(dim=-1), rtol=1e-12)


def test_torch_tiles_agree(monkeypatch: pytest.MonkeyPatch) -> None:
    pos = _positions(2, 150, seed=4)
    whole = knn_graph(pos, BOX, method="torch")
    monkeypatch.setattr(knn_module, "_PAIR_BUDGET", 7 * 150)  # 7 receivers per tile, one sample at a time
    tiled = knn_graph(pos, BOX, method="torch")
    assert torch.equal(whole.edge_index, tiled.edge_index)


def test_knn_clips_k_and_aggregates() -> None:
    pos = _positions(2, 5, seed=2)
    graph = knn_graph(pos, BOX, k=15)
    assert graph.n_edges == 2 * 5 * 4  # k clipped to N - 1
    agg = sum_aggregate(torch.ones(2, 5, 1), graph.as_batched())
    assert torch.equal(agg, torch.full((2, 5, 1), 4.0))


def test_full_graph() -> None:
    b, n = 2, 7
    pos = _positions(b, n, seed=3)
    graph = full_graph(pos, BOX)
    src, dst = graph.edge_index
    assert graph.n_edges == b * n * (n - 1) and graph.edges_per_node == n - 1
    assert not (src == dst).any() and torch.equal(src // n, dst // n)
    pairs = set(zip(src.tolist(), dst.tolist(), strict=True))
    assert len(pairs) == graph.n_edges
    assert all((d, s) in pairs for s, d in pairs)  # both directions
    # minimum-image vectors are exactly antisymmetric and no component exceeds L/2
    lookup = {p: i for i, p in enumerate(zip(src.tolist(), dst.tolist(), strict=True))}
    rev = torch.tensor([lookup[(d, s)] for s, d in zip(src.tolist(), dst.tolist(), strict=True)])
    assert torch.equal(graph.edge_vec, -graph.edge_vec[rev])
    assert (graph.edge_vec.abs() <= BOX / 2).all()
    dist = _brute_distances(pos[0].numpy(), BOX)
    mask = (src < n).numpy()
    lengths = graph.edge_vec[mask].norm(dim=-1).numpy()
    np.testing.assert_allclose(lengths, dist[src[mask], dst[mask]], rtol=1e-12)


def test_wrap_and_minimum_image() -> None:
    x = torch.tensor([-5.0, 4.999, 5.0, 15.2, -25.1], dtype=torch.float64)
    w = wrap_positions(x, BOX)
    assert ((w >= -5) & (w < 5)).all()
    assert torch.allclose(w, torch.tensor([-5.0, 4.999, -5.0, -4.8, 4.9], dtype=torch.float64))
    d = torch.tensor([6.0, -6.0, 4.0, 14.0], dtype=torch.float64)
    assert torch.allclose(minimum_image(d, BOX), torch.tensor([-4.0, 4.0, 4.0, 4.0], dtype=torch.float64))
    assert torch.equal(minimum_image(-d, BOX), -minimum_image(d, BOX))
