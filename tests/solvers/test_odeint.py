import math

import pytest
import torch
from torch import nn

from mpsim.errors import ConfigError, DivergenceError
from mpsim.solvers import ODESolver


class Oscillator(nn.Module):
    """ẍ = −ω²x: closed form x = cos ωt, v = −ω sin ωt from (1, 0)."""

    def __init__(self, omega: float = 2.0):
        super().__init__()
        self.omega = omega

    def forward(self, t, y):  # y: [B, 2]
        return torch.stack([y[..., 1], -(self.omega**2) * y[..., 0]], dim=-1)


def _exact(t, omega=2.0):
    return torch.stack([torch.cos(omega * t), -omega * torch.sin(omega * t)], dim=-1)


@pytest.mark.parametrize("method", ["dopri5", "rk4"])
def test_matches_closed_form_batch_first(method):
    t = torch.linspace(0, 3, 301, dtype=torch.float64)
    y0 = torch.tensor([[1.0, 0.0]] * 3, dtype=torch.float64)
    ys = ODESolver(method, rtol=1e-9, atol=1e-9)(Oscillator(), y0, t)
    assert ys.shape == (3, 301, 2)
    assert torch.allclose(ys[0], _exact(t), atol=1e-6)


def test_rk4_converges_at_fourth_order():
    errors = []
    for n in (20, 40, 80):
        t = torch.linspace(0, 2, n + 1, dtype=torch.float64)
        ys = ODESolver("rk4")(Oscillator(), torch.tensor([[1.0, 0.0]], dtype=torch.float64), t)
        errors.append(float((ys[0, -1] - _exact(t)[-1]).abs().max()))
    orders = [math.log2(errors[i] / errors[i + 1]) for i in range(2)]
    assert all(3.7 < p < 4.3 for p in orders), orders


def test_blow_up_is_a_divergence_error():
    class Blowup(nn.Module):
        def forward(self, t, y):
            return y**2  # y = 1 / (1 − t) from y0 = 1: infinite at t = 1

    with pytest.raises(DivergenceError, match="stiff or blew up"):
        ODESolver("dopri5", max_num_steps=200)(
            Blowup(), torch.ones(1, 1, dtype=torch.float64), torch.tensor([0.0, 2.0], dtype=torch.float64)
        )


def test_unknown_method_lists_choices():
    with pytest.raises(ConfigError, match="dopri5"):
        ODESolver("tsit5")


def test_adjoint_gradients_match_backprop():
    torch.manual_seed(0)
    net = nn.Sequential(nn.Linear(2, 8), nn.Tanh(), nn.Linear(8, 2)).double()

    class Field(nn.Module):
        def __init__(self):
            super().__init__()
            self.net = net

        def forward(self, t, y):
            return self.net(y)

    y0 = torch.randn(3, 2, dtype=torch.float64)
    t = torch.linspace(0, 1, 5, dtype=torch.float64)
    grads = []
    for adjoint in (False, True):
        net.zero_grad()
        ODESolver("dopri5", rtol=1e-9, atol=1e-9, adjoint=adjoint)(Field(), y0, t).pow(2).sum().backward()
        grads.append(torch.cat([p.grad.flatten() for p in net.parameters()]))
    assert torch.allclose(grads[0], grads[1], rtol=1e-5, atol=1e-7)
