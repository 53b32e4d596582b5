"""Controls of learned vector fields: z-scoring fitted once from training data, zero-order hold."""

import torch

from mpsim.data.trajectories import Inputs, Trajectories
from mpsim.graphs.topology import complete
from mpsim.metrics import huber_loss
from mpsim.models import MPNODE
from mpsim.models.controls import ControlNormalisation, zero_order_hold


def test_zero_order_hold_takes_the_sample_at_or_before_t():
    t = torch.tensor([0.0, 0.1, 0.2])
    u = torch.arange(3.0).reshape(1, 3, 1, 1)
    assert zero_order_hold(t, u, torch.tensor(0.0)).item() == 0.0
    assert zero_order_hold(t, u, torch.tensor(0.0999)).item() == 0.0
    assert zero_order_hold(t, u, torch.tensor(0.1)).item() == 1.0
    assert zero_order_hold(t, u, torch.tensor(0.35)).item() == 2.0
    assert zero_order_hold(t, None, torch.tensor(0.1)) is None


def test_normalisation_is_fitted_once_and_travels_in_the_state_dict():
    norm = ControlNormalisation(2)
    u = torch.stack([3.3 + 0.2 * torch.randn(500), torch.full((500,), 1.0)], dim=-1)
    assert torch.equal(norm(u), u)  # identity until fitted
    norm.fit_once(u)
    z = norm(u)
    assert abs(float(z[:, 0].mean())) < 1e-5 and abs(float(z[:, 0].std()) - 1) < 1e-4
    assert torch.allclose(z[:, 1], torch.zeros(500))  # a constant channel is only centred
    norm.fit_once(10 * u)  # frozen once fitted (a finetune keeps the checkpoint's statistics)
    assert torch.allclose(norm(u), z)
    assert set(norm.state_dict()) == {"mean", "std", "fitted"}
    assert ControlNormalisation(0).state_dict() == {}


def test_mpnode_without_controls_keeps_its_checkpoint_keys():
    assert not any(k.startswith("controls") for k in MPNODE(3).state_dict())


def test_mpnode_fits_its_control_scale_on_the_first_training_batch():
    torch.manual_seed(0)
    model = MPNODE(2, control_dim=4)
    t = torch.linspace(0, 0.5, 6)
    batch = Trajectories(t=t, x=torch.randn(8, 6, 3, 2), edge_index=complete(3), u=3.3 + 0.2 * torch.randn(8, 6, 3, 4))
    loss, pred = model.training_loss(batch, t, huber_loss)
    assert bool(model.controls.fitted) and torch.allclose(model.controls.mean, batch.u.mean((0, 1, 2)), atol=1e-5)
    loss.backward()
    assert pred.shape == batch.x.shape


def test_mpnode_prediction_at_a_sample_time_ignores_that_samples_input():
    # zero-order hold: u_k acts on [t_k, t_{k+1}), so x̂(t_k) cannot depend on u_k (causality)
    torch.manual_seed(0)
    model = MPNODE(2, control_dim=1).double()
    x0 = torch.randn(1, 3, 2, dtype=torch.float64)
    t = torch.linspace(0, 1, 5, dtype=torch.float64)
    u = torch.zeros(1, 5, 3, 1, dtype=torch.float64)
    late = u.clone()
    late[:, 3:] = 1.0
    base, changed = model.rollout(x0, t, Inputs(complete(3), u=u)), model.rollout(x0, t, Inputs(complete(3), u=late))
    assert torch.equal(base[:, :4], changed[:, :4]) and not torch.allclose(base[:, 4], changed[:, 4])


def test_control_statistics_follow_a_refit_of_the_state_statistics():
    torch.manual_seed(0)
    model = MPNODE(2, control_dim=1)
    t = torch.linspace(0, 0.2, 3)
    batch = Trajectories(t=t, x=torch.randn(4, 3, 2, 2), edge_index=complete(2), u=3.0 + torch.randn(4, 3, 2, 1))
    model.training_loss(batch, t, huber_loss)
    old = model.controls.mean.clone()
    model.set_normalisation(torch.zeros(2), torch.ones(2))  # what mode.refit_normalisation=true does
    assert not bool(model.controls.fitted) and torch.equal(model.controls.mean, old)  # in use until refit
    shifted = Trajectories(t=t, x=batch.x, edge_index=batch.edge_index, u=batch.u - 1.0)
    model.training_loss(shifted, t, huber_loss)
    assert torch.allclose(model.controls.mean, old - 1.0, atol=1e-5)
