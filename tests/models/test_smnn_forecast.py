"""S-MNN forecaster: the layer's linear ODE, persistence at init, context handling, graphs, training."""

from __future__ import annotations

import pytest
import torch

from mpsim.data.dataset import fit_normalisation
from mpsim.data.trajectories import Inputs
from mpsim.errors import ConfigError
from mpsim.graphs.topology import chain, complete
from mpsim.metrics import huber_loss
from mpsim.models.smnn_forecast import SMNNForecaster
from mpsim.systems.pendulum import CoupledPendulums

F64 = torch.float64


@pytest.fixture(scope="module")
def pendulums():
    return CoupledPendulums(name="pendulum2", n_nodes=2).generate(12, seed=0, dt=0.1, horizon=30)


def test_layer_solves_the_linear_ode_the_encoder_writes():
    """u' = A u + r with constant r: the chunk must match the exact solution (sign and layout of A)."""
    model = SMNNForecaster(state_dim=2, chunk=20, n_orders=4).double()
    A = torch.tensor([[-0.05, 0.1], [-0.1, -0.05]], dtype=F64)
    r = torch.tensor([0.02, -0.01], dtype=F64)
    u0 = torch.tensor([1.0, 0.5], dtype=F64)
    out = model.solve_chunk(A.expand(1, 1, 2, 2), r.expand(1, 1, 21, 2), u0.expand(1, 1, 2), 1.0)
    tau = torch.arange(1, 21, dtype=F64)
    fixed = -torch.linalg.solve(A, r)  # u(τ) = x* + e^{Aτ}(u0 − x*)
    exact = fixed + torch.einsum("tij,j->ti", torch.linalg.matrix_exp(A * tau[:, None, None]), u0 - fixed)
    assert out.shape == (1, 20, 1, 2)
    assert torch.allclose(out[0, :, 0], exact, atol=1e-3)  # the layer discretises at one step per sample


def test_untrained_model_is_persistence_and_keeps_the_context(pendulums):
    model = SMNNForecaster(state_dim=2, context_steps=5, chunk=4).double()
    model.set_normalisation(*fit_normalisation(pendulums))
    x = pendulums.x
    pred = model.rollout(x[:, :5], pendulums.t, Inputs(pendulums.edge_index))
    assert pred.shape == x.shape
    assert torch.equal(pred[:, :5], x[:, :5])  # the context is returned as given
    assert torch.allclose(pred[:, 5:], x[:, 4:5].expand_as(pred[:, 5:]), atol=1e-10)  # A = 0, r = 0


def test_context_of_one_state_and_wrong_context_length(pendulums):
    model = SMNNForecaster(state_dim=2, context_steps=1, chunk=7).double()
    pred = model.rollout(pendulums.x[:, 0], pendulums.t, Inputs(pendulums.edge_index))  # x0: [B, N, D]
    assert pred.shape == pendulums.x.shape
    with pytest.raises(ConfigError, match="context"):
        SMNNForecaster(state_dim=2, context_steps=3).rollout(
            pendulums.x[:, :2].float(), pendulums.t.float(), Inputs(pendulums.edge_index)
        )


def test_runs_on_any_graph_and_with_controls():
    torch.manual_seed(0)
    model = SMNNForecaster(state_dim=3, control_dim=2, context_steps=4, chunk=3, hidden=16)
    with torch.no_grad():
        model.encoder[-1].weight.normal_(0, 0.1)
    t = torch.arange(12) * 0.05
    for n, edges in ((2, complete(2)), (7, chain(7))):
        x = torch.randn(3, 4, n, 3)
        u = torch.randn(3, 12, n, 2)
        pred = model.rollout(x, t, Inputs(edges, u=u))
        assert pred.shape == (3, 12, n, 3) and torch.isfinite(pred).all()
    # the controls of the predicted chunk reach the prediction
    other = model.rollout(x, t, Inputs(edges, u=u + 1.0))
    assert not torch.allclose(other[:, 4:], pred[:, 4:])


def test_training_beats_persistence_and_random_starts(pendulums):
    torch.manual_seed(0)
    model = SMNNForecaster(state_dim=2, context_steps=5, chunk=5, hidden=32, train_steps=10).double()
    model.set_normalisation(*fit_normalisation(pendulums))
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    first = None
    for _ in range(60):
        loss, pred = model.training_loss(pendulums, pendulums.t, huber_loss)
        assert pred.shape == (12, 15, 2, 2)  # K + train_steps states from a random start
        first = float(loss.detach()) if first is None else first
        opt.zero_grad()
        loss.backward()
        opt.step()
        model.after_step()
    assert float(loss.detach()) < 0.3 * first
    # full-horizon error below the persistence forecast the model started from
    with torch.no_grad():
        pred = model.rollout(pendulums.x[:, :5], pendulums.t, Inputs(pendulums.edge_index))
    err = (pred[:, 5:] - pendulums.x[:, 5:]).pow(2).mean()
    persistence = (pendulums.x[:, 4:5] - pendulums.x[:, 5:]).pow(2).mean()
    assert float(err) < 0.5 * float(persistence)


def test_whole_state_couples_every_node_and_keeps_its_graph_size(pendulums):
    model = SMNNForecaster(state_dim=2, context_steps=3, chunk=4, hidden=16, whole_state=True, n_nodes=2).double()
    model.set_normalisation(*fit_normalisation(pendulums))
    assert model.encoder[0].in_features == 3 * 4 + 4 and not model.transfers_across_graphs
    x = pendulums.x
    assert torch.allclose(
        model.rollout(x[:, :3], pendulums.t, Inputs(pendulums.edge_index))[:, 3:],
        x[:, 2:3].expand_as(x[:, 3:]),
        atol=1e-10,
    )  # untrained: persistence
    with torch.no_grad():
        model.encoder[-1].weight.normal_(0, 0.1)
    pred = model.rollout(x[:, :3], pendulums.t, Inputs(pendulums.edge_index))
    moved = x[:, :3].clone()
    moved[:, :, 1] += 0.5  # node 1's past changes node 0's forecast: one ODE for the whole state
    other = model.rollout(moved, pendulums.t, Inputs(pendulums.edge_index))
    assert not torch.allclose(other[:, 3:, 0], pred[:, 3:, 0])
    with pytest.raises(ConfigError, match="built for 2 nodes"):
        model.rollout(torch.zeros(1, 3, 3, 2, dtype=F64), pendulums.t, Inputs(complete(3)))
    with pytest.raises(ConfigError, match="n_nodes"):
        SMNNForecaster(state_dim=2, whole_state=True)


def test_bad_configs_are_refused():
    with pytest.raises(ConfigError, match="solver_method"):
        SMNNForecaster(state_dim=2, solver_method="lu")
    with pytest.raises(ConfigError, match="chunk"):
        SMNNForecaster(state_dim=2, chunk=0)
