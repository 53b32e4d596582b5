"""DeltaGN: paper parameter counts, symmetries in the periodic box, one-step training, rollouts at other N."""

from __future__ import annotations

import json
import math

import pytest
import torch

from mpsim.data.trajectories import Inputs, Trajectories
from mpsim.errors import IncompatibleError
from mpsim.models.deltagn import DeltaGN
from mpsim.systems.nbody import NBody
from tests.helpers import run_cli

GRAPHS = ["full", "knn", "hierarchical"]


@pytest.fixture(scope="module")
def data() -> Trajectories:
    """Four float64 trajectories of 20 gravitating particles, 12 steps."""
    return NBody(n_particles=20, n_steps=12).generate(4, seed=0)


def _model(graph: str, **kw) -> DeltaGN:
    torch.manual_seed(0)
    return DeltaGN(graph=graph, k=6, **kw).double().eval()


def _shifted(x: torch.Tensor, shift: torch.Tensor, box: float) -> torch.Tensor:  # x: [..., 4]
    pos = x[..., :2] + shift
    return torch.cat([pos - box * torch.floor(pos / box + 0.5), x[..., 2:]], dim=-1)


def _close_on_torus(a: torch.Tensor, b: torch.Tensor, box: float, atol: float) -> bool:
    d = a - b
    d[..., :2] -= box * torch.round(d[..., :2] / box)
    return bool(d.abs().max() < atol)


@pytest.mark.parametrize(
    ("graph", "charge", "expected"),
    [
        ("full", False, 60_254),
        ("knn", False, 60_254),
        ("hierarchical", False, 285_604),
        ("hierarchical", True, 287_404),
    ],
)
def test_parameter_counts_match_the_reference(graph: str, charge: bool, expected: int) -> None:
    assert sum(p.numel() for p in DeltaGN(graph=graph, charge=charge).parameters()) == expected


@pytest.mark.parametrize("graph", GRAPHS)
def test_step_is_permutation_equivariant(graph: str, data: Trajectories) -> None:
    model = _model(graph)
    x, nf, box = data.x[:2, 3], data.node_features[:2], data.meta["box_size"]
    perm = torch.randperm(20, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        a = model.step(x, nf, box, 0.01)
        b = model.step(x[:, perm], nf[:, perm], box, 0.01)
    assert torch.allclose(a[:, perm], b, atol=1e-10)


@pytest.mark.parametrize("graph", GRAPHS)
def test_translation_invariant_in_the_periodic_box(graph: str, data: Trajectories) -> None:
    """Full and kNN graphs: any shift. The quadtree is fixed in space, so the hierarchy is exactly invariant
    under shifts by whole top-level (L/4) cells, which map every level's cells onto cells."""
    model = _model(graph)
    x, nf, box = data.x[:2, 5], data.node_features[:2], data.meta["box_size"]
    shift = (
        torch.tensor([box / 4, -box / 2], dtype=torch.float64)
        if graph == "hierarchical"
        else torch.tensor([0.37 * box, -1.91], dtype=torch.float64)
    )
    with torch.no_grad():
        a = model.step(x, nf, box, 0.01)
        b = model.step(_shifted(x, shift, box), nf, box, 0.01)
    assert _close_on_torus(_shifted(a, shift, box), b, box, 1e-9)


def test_one_step_loss_takes_positions_by_minimum_image(data: Trajectories) -> None:
    """A prediction that equals the target up to whole box widths costs nothing."""
    model = _model("knn")
    box = data.meta["box_size"]
    calls = {}

    def exact_but_shifted(x, nf, box_, dt):  # the true next state, one box width to the right
        calls["dt"] = dt
        b = x.shape[0]
        nxt = torch.stack([data.x[i // model.pairs_per_trajectory] for i in range(b)])  # [b, T, N, 4]
        match = (nxt == x[:, None]).all(-1).all(-1)  # which stored state each input is
        out = nxt[torch.arange(b), match.float().argmax(1) + 1].clone()
        out[..., 0] += box
        return out

    model.step = exact_but_shifted
    loss, pred = model.training_loss(data, data.t, None)
    assert pred.shape == (4, model.pairs_per_trajectory, 20, 4)
    assert float(loss) < 1e-20 and calls["dt"] == pytest.approx(0.01)


def test_training_fits_the_output_scale_once_and_learns(data: Trajectories) -> None:
    torch.manual_seed(0)
    model = DeltaGN(graph="hierarchical", pairs_per_trajectory=4)
    batch = data.to(dtype=torch.float32)
    t = batch.t.float()
    opt = torch.optim.Adam(model.parameters(), 3e-3)
    losses = []
    for _ in range(30):
        loss, _ = model.training_loss(batch, t, None)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    scale = model.delta_scale.clone()
    assert bool(model.delta_scale_fitted) and scale[0] == scale[1] and scale[2] == scale[3]
    assert 1e-4 < float(scale[0]) < 0.1 and float(model.trained_dt) == pytest.approx(0.01)
    assert int(model.pair_draws) == 30
    assert sum(losses[-5:]) < sum(losses[:5])
    model.training_loss(batch, t, None)
    assert torch.equal(model.delta_scale, scale)  # fitted once, then frozen (and saved in the state dict)
    assert "delta_scale" in model.state_dict() and "pair_draws" in model.state_dict()


def test_trained_at_one_n_runs_at_another() -> None:
    """Box size and hierarchy depth come from the data at run time."""
    torch.manual_seed(0)
    model = DeltaGN(graph="hierarchical", pairs_per_trajectory=2)
    small = NBody(n_particles=20, n_steps=4).generate(2, seed=0).to(dtype=torch.float32)
    loss, _ = model.training_loss(small, small.t.float(), None)
    loss.backward()
    big = NBody(n_particles=70, n_steps=3).generate(2, seed=1).to(dtype=torch.float32)
    model.eval()
    with torch.no_grad():
        pred = model.rollout(big.x[:, 0], big.t.float(), big.inputs())
    assert pred.shape == (2, 4, 70, 4) and torch.isfinite(pred).all()
    assert (pred[..., :2].abs() <= big.meta["box_size"] / 2).all()
    report = model.report()["nbody"]
    assert report["graph"] == "hierarchical" and report["energy_trajectories"] == 2
    assert set(report["energy_error"]) == {"3"}  # both horizons clip to the 3-step rollout


def test_refuses_other_dt_charges_and_missing_box(data: Trajectories) -> None:
    model = _model("knn")
    model.trained_dt.fill_(0.02)
    with pytest.raises(IncompatibleError, match="dt = 0.02"), torch.no_grad():
        model.rollout(data.x[:, 0], data.t, data.inputs())
    model.trained_dt.zero_()
    charged = data.node_features.clone()
    charged[..., 1] = 1.0
    with pytest.raises(IncompatibleError, match="model.charge=true"), torch.no_grad():
        model.rollout(data.x[:, 0], data.t, Inputs(data.edge_index, node_features=charged, meta=data.meta))
    with pytest.raises(IncompatibleError, match="box_size"), torch.no_grad():
        model.rollout(data.x[:, 0], data.t, Inputs(data.edge_index, node_features=data.node_features, meta={}))
    with pytest.raises(IncompatibleError, match=r"state \(x, y, vx, vy\)"):
        DeltaGN(state_dim=3).check_compatible(3, 0, 20)


def test_divergence_is_reported_per_trajectory(data: Trajectories) -> None:
    """A trajectory that turns NaN stays NaN; the others are unaffected."""
    model = _model("knn")
    advance = model.advance

    def poisoned(x, nf, graph, box, dt):
        out = advance(x, nf, graph, box, dt)
        out[1, 0, 2] = math.inf  # trajectory 1 blows up at every step
        return out

    model.advance = poisoned
    with torch.no_grad():
        pred = model.rollout(data.x[:, 0], data.t, data.inputs())
    assert torch.isnan(pred[1, 1:]).all() and torch.isfinite(pred[[0, 2, 3]]).all()
    report = model.report()["nbody"]
    assert math.isfinite(report["energy_error"]["12"])  # the finite trajectories still count


@pytest.mark.slow
def test_train_then_eval_at_another_n_end_to_end(tmp_path) -> None:
    tiny = [
        "trainer=quick",
        "trainer.progress=false",
        "trainer.max_epochs=1",
        "trainer.batch_size=2",
        "data.n_train=4",
        "data.n_val=1",
        "data.n_test=2",
        "data.horizon=20",
        "eval.plots=false",
    ]
    run_cli(["train", "system=nbody20", "model=deltagn", "model.pairs_per_trajectory=2", *tiny], tmp_path, check=True)
    (summary,) = list((tmp_path / "outputs" / "train").rglob("summary.json"))
    s = json.loads(summary.read_text())
    assert s["model"]["n_params"] == 285_604 and s["model"]["nbody"]["graph"] == "hierarchical"
    assert set(s["test"]["horizons"]) == {"1", "20"} and s["test"]["n_diverged"] == 0
    assert s["model"]["nbody"]["energy_error"]["20"] > 0 and "data_energy_drift" in s["model"]["nbody"]
    proc = run_cli(
        [
            "eval",
            "init=nbody20.ckpt",
            "system=nbody100",
            "data.n_train=1",
            "data.n_val=1",
            "data.n_test=2",
            "data.horizon=5",
            "eval.plots=false",
        ],
        tmp_path,
        check=True,
    )
    assert "energy error |ΔH/H0|" in proc.stdout
    (ev,) = list((tmp_path / "outputs" / "eval").rglob("summary.json"))
    e = json.loads(ev.read_text())
    assert e["trained_on"] == "nbody20" and e["system"]["n_nodes"] == 100


@pytest.mark.parametrize("graph", ["knn", "hierarchical"])
def test_spatial_reordering_changes_nothing_but_speed(graph: str) -> None:
    """Particles renumbered along the Z-order curve (the default) give the un-reordered step to float rounding,
    in the caller's particle order, and the same training gradients."""
    model = _model(graph)
    data = NBody(n_particles=300, n_steps=1).generate(2, seed=5)
    x, nf, box = data.x[:, 1], data.node_features, data.meta["box_size"]
    graph_sorted = model.build_graph(x[..., :2], nf, x[..., 2:], box)
    order = graph_sorted.order
    assert order is not None and not torch.equal(order, torch.arange(600))
    assert torch.equal(order // 300, torch.arange(2).repeat_interleave(300))  # a permutation within samples
    runs = {}
    for reorder in (True, False):
        model.reorder_particles = reorder
        model.zero_grad()
        out = model.step(x, nf, box, 0.01)
        out.pow(2).sum().backward()
        runs[reorder] = (out.detach(), [p.grad.clone() for p in model.parameters()])
    assert model.build_graph(x[..., :2], nf, x[..., 2:], box).order is None
    (a, grads_a), (b, grads_b) = runs[True], runs[False]
    assert torch.allclose(a, b, rtol=0, atol=1e-12)
    for ga, gb in zip(grads_a, grads_b, strict=True):
        assert torch.allclose(ga, gb, rtol=1e-10, atol=1e-12)
