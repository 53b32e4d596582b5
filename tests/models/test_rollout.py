import math

import pytest
import torch

from mpsim.data.trajectories import Trajectories
from mpsim.errors import DivergenceError
from mpsim.metrics import rollout_metrics
from mpsim.models.base import Model
from mpsim.models.rollout import rollout, rollout_error


class Drift(Model):
    """x(t) = x0 + v·t with a learnable v; diverges on any batch whose first state holds a value above 100, and
    reports its drift as an auxiliary signal."""

    def __init__(self) -> None:
        super().__init__(state_dim=2)
        self.v = torch.nn.Parameter(torch.tensor([0.5, -1.0]))

    def rollout(self, x0, t, inputs):  # x0: [B, N, D] -> [B, T, N, D]
        if (x0 > 100).any():
            raise DivergenceError("step size underflow")
        return x0.unsqueeze(1) + t.reshape(1, -1, 1, 1) * self.v

    def rollout_aux(self, x0, t, inputs):
        pred = self.rollout(x0, t, inputs)
        return pred, {"drift": pred - x0.unsqueeze(1)}


def _data(n: int = 5) -> Trajectories:
    t = torch.linspace(0.0, 1.0, 4, dtype=torch.float64)
    x0 = torch.arange(n * 3 * 2, dtype=torch.float64).reshape(n, 1, 3, 2)
    return Trajectories(t=t, x=x0 + t.reshape(1, -1, 1, 1), edge_index=torch.zeros(2, 0, dtype=torch.long))


def test_rollout_predicts_every_trajectory_in_batches_without_gradients():
    data, model = _data(), Drift()
    pred, aux = rollout(model, data, batch_size=2)
    expected = data.x[:, :1].float() + data.t.float().reshape(1, -1, 1, 1) * model.v.detach()
    assert pred.shape == data.x.shape and pred.dtype == torch.float32 and not pred.requires_grad
    assert torch.allclose(pred, expected) and aux == {}
    assert torch.equal(pred, rollout(model, data)[0])  # one batch or three: the same numbers
    pred_aux, aux = rollout(model, data, batch_size=2, aux=True)
    assert torch.equal(pred_aux, pred) and torch.allclose(aux["drift"], pred - pred[:, :1])


def test_a_batch_that_diverges_is_nan_and_the_others_are_kept():
    data = _data()
    data.x[3, 0, 0, 0] = 1000.0  # the second batch of two (trajectories 2 and 3) cannot be solved
    pred, aux = rollout(Drift(), data, batch_size=2, aux=True)
    assert pred[2:4].isnan().all() and torch.isfinite(pred[[0, 1, 4]]).all()
    assert aux == {}  # a batch without signals: none are merged


def test_rollout_error_is_the_normalised_rmse_after_the_first_state():
    data, model = _data(), Drift()
    model.set_normalisation(torch.zeros(2), torch.tensor([2.0, 4.0]))
    pred, _ = rollout(model, data)
    rmse = rollout_metrics(pred, data.x.float(), model.state_std, data.t)["rmse"]
    assert rollout_error(model, data) == rmse == rollout_error(model, data, pred=pred)
    err = ((pred - data.x.float())[:, 1:] / model.state_std).pow(2).mean().sqrt()
    assert math.isclose(rmse, float(err), rel_tol=1e-6)
    assert math.isnan(rollout_error(model, data, pred=torch.full_like(pred, math.nan)))


def _partly_measured(data: Trajectories) -> Trajectories:
    """`data` with its second state latent (meta['observed'] names the first), that state's values after the first
    sample corrupted: an estimate nobody should fit to."""
    x = data.x.clone()
    x[:, 1:, :, 1] += 1e3
    meta = {**data.meta, "state_names": ["q", "v"], "observed": ["q"]}
    return Trajectories(t=data.t, x=x, edge_index=data.edge_index, meta=meta)


def test_losses_and_errors_on_the_measured_states_ignore_a_corrupted_latent_one():
    from mpsim.metrics import mse_loss

    data, model = _data(), Drift()
    latent = _partly_measured(data)
    assert latent.observed_index == [0] and latent.latent_index == [1] and data.observed_index == [0, 1]
    t = data.t.float()
    with torch.no_grad():
        loss, _ = model.training_loss(latent.to(dtype=torch.float32), t, mse_loss)
        pred = model.rollout(data.x[:, 0].float(), t, data.inputs())
        assert float(loss) == pytest.approx(float(mse_loss(pred[..., :1], data.x[..., :1].float())))
        assert float(model.training_loss(data.to(dtype=torch.float32), t, mse_loss)[0]) != pytest.approx(float(loss))
    err = rollout_error(model, latent)
    expected = rollout_metrics(pred, data.x.float(), model.state_std, data.t, features=[0])["rmse"]
    assert err == pytest.approx(expected) and err < 1.0
    every = Trajectories(t=latent.t, x=latent.x, edge_index=latent.edge_index)  # no meta: every state is a target
    assert rollout_error(model, every) > 100.0
