"""HOGN: paper parameter counts, one Hamiltonian per sample, conservation of its own energy under RK4."""

from __future__ import annotations

import math

import pytest
import torch

from mpsim.data.trajectories import Inputs
from mpsim.models.hogn import HOGN
from mpsim.systems.nbody import NBody


def _model(graph: str, charge: bool = False) -> HOGN:
    torch.manual_seed(0)
    return HOGN(graph=graph, k=6, charge=charge).double().eval()


@pytest.mark.parametrize(("graph", "expected"), [("full", 94_901), ("knn", 94_901), ("hierarchical", 319_501)])
def test_parameter_counts_match_the_reference(graph: str, expected: int) -> None:
    assert sum(p.numel() for p in HOGN(graph=graph).parameters()) == expected


@pytest.mark.parametrize("graph", ["full", "hierarchical"])
def test_one_hamiltonian_per_sample(graph: str) -> None:
    """Batching two samples gives exactly the two separate runs (the reference mixed the batch, spec §7.1)."""
    model = _model(graph, charge=True)
    data = NBody(n_particles=24, force="coulomb", n_steps=2).generate(2, seed=3)
    x, nf, box = data.x[:, 1], data.node_features, data.meta["box_size"]
    together_h = model.energy_of(x, nf, box)
    together = model.step(x, nf, box, 0.01)
    assert together_h.shape == (2,)
    for s in range(2):
        alone_h = model.energy_of(x[s : s + 1], nf[s : s + 1], box)
        alone = model.step(x[s : s + 1], nf[s : s + 1], box, 0.01)
        assert torch.allclose(together_h[s], alone_h[0], rtol=1e-12, atol=1e-12)
        assert torch.allclose(together[s], alone[0], atol=1e-12)


def test_conserves_its_own_energy_to_rk4_accuracy() -> None:
    """On a fixed graph the learned H is a smooth function of (q, p) and RK4 keeps it to O(dt^4) per unit
    time; with the sign of either Hamilton equation flipped, H would change at O(1)."""
    model = _model("full")
    with torch.no_grad():
        model.decode.weight.mul_(100.0)  # untrained H is nearly flat: give it speeds ~1 and forces ~0.5
    g = torch.Generator().manual_seed(0)
    n, box = 6, 40.0  # a loose cluster in a big box: no separation crosses L/2 (a minimum-image kink)
    pos = torch.randn(1, n, 2, generator=g, dtype=torch.float64)
    vel = torch.randn(1, n, 2, generator=g, dtype=torch.float64) * 0.5
    x0, nf = torch.cat([pos, vel], dim=-1), torch.ones(1, n, 2, dtype=torch.float64)
    nf[..., 1] = 0.0
    meta = {"box_size": box}

    def drift(dt: float, steps: int) -> float:
        t = torch.arange(steps + 1, dtype=torch.float64) * dt
        with torch.no_grad():
            pred = model.rollout(x0, t, Inputs(torch.zeros(2, 0, dtype=torch.long), node_features=nf, meta=meta))
        h = model.energy_of(pred[0], nf.expand(steps + 1, n, 2), box).detach()
        return float((h - h[0]).abs().max() / h[0].abs())

    coarse, fine = drift(0.2, 10), drift(0.1, 20)
    assert coarse < 1e-8
    assert coarse / fine > 10  # fourth order: 16 expected


def test_any_time_step_and_translation_invariance() -> None:
    model = _model("full")
    data = NBody(n_particles=16, n_steps=3, dt=0.02).generate(1, seed=1)
    box = data.meta["box_size"]
    model.trained_dt.fill_(0.01)  # trained at another step: an ODE model integrates any dt
    with torch.no_grad():
        pred = model.rollout(data.x[:, 0], data.t, data.inputs())
    assert torch.isfinite(pred).all() and pred.shape == (1, 4, 16, 4)
    x, nf = data.x[:, 0], data.node_features
    shift = torch.tensor([0.3 * box, -2.7], dtype=torch.float64)
    moved = torch.cat([x[..., :2] + shift, x[..., 2:]], dim=-1)
    a = model.step(x, nf, box, 0.01)
    b = model.step(moved, nf, box, 0.01)
    d = b - a
    d[..., :2] -= shift
    d[..., :2] -= box * torch.round(d[..., :2] / box)
    assert d.abs().max() < 1e-9


def test_training_step_differentiates_through_the_hamiltonian() -> None:
    torch.manual_seed(0)
    model = HOGN(graph="hierarchical", pairs_per_trajectory=1)
    data = NBody(n_particles=70, n_steps=3).generate(1, seed=0).to(dtype=torch.float32)
    loss, pred = model.training_loss(data, data.t.float(), None)
    loss.backward()
    # every parameter but the decoder's bias (a constant shift of H moves nothing) gets a gradient; N = 70
    # has two cell levels, so the upward and downward cell-to-cell MLPs are used too
    grads = [p.grad for name, p in model.named_parameters() if name != "decode.bias"]
    assert all(g is not None for g in grads) and pred.shape == (1, 1, 70, 4)
    assert math.isfinite(float(loss.detach())) and sum(float(g.abs().sum()) for g in grads) > 0


@pytest.mark.parametrize("graph", ["knn", "hierarchical"])
def test_spatial_reordering_changes_nothing_but_speed(graph: str) -> None:
    """The Z-order renumbering gives the un-reordered RK4 step and Hamiltonian, in the caller's order."""
    model = _model(graph, charge=True)
    data = NBody(n_particles=200, force="coulomb", n_steps=1).generate(2, seed=4)
    x, nf, box = data.x[:, 1], data.node_features, data.meta["box_size"]
    order = model.build_graph(x[..., :2], nf, x[..., 2:], box).order
    # a real renumbering: a permutation of the 2 x 200 particles that keeps each sample's own and moves most
    assert order is not None and torch.equal(order.sort().values, torch.arange(400))
    assert torch.equal(order.view(2, 200) // 200, torch.tensor([[0], [1]]).expand(2, 200))
    assert (order != torch.arange(400)).float().mean() > 0.5
    a, ha = model.step(x, nf, box, 0.01), model.energy_of(x, nf, box)
    model.reorder_particles = False
    assert model.build_graph(x[..., :2], nf, x[..., 2:], box).order is None  # b below is the plain order's
    b, hb = model.step(x, nf, box, 0.01), model.energy_of(x, nf, box)
    assert torch.allclose(a, b, rtol=0, atol=1e-12)
    assert torch.allclose(ha, hb, rtol=1e-12, atol=1e-12)
