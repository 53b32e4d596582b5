import pytest
import torch
from torch import nn

from mpsim.models import layers
from mpsim.models.layers import ACTIVATIONS, Tanh, mlp


def test_tanh_is_tanh_to_rounding_over_the_whole_range_and_at_the_limits():
    x = torch.linspace(-40.0, 40.0, 200_001)
    exact = torch.tanh(x.double())
    assert (Tanh()(x).double() - exact).abs().max() < 3e-7  # float32: torch's own kernel is 3e-8 off
    assert (Tanh()(x.double()) - exact).abs().max() < 1e-15
    edges = Tanh()(torch.tensor([float("inf"), -float("inf"), float("nan"), 0.0]))
    assert edges[:2].tolist() == [1.0, -1.0] and edges[2].isnan() and edges[3] == 0.0


def test_tanh_gradients_are_tanh_gradients_once_and_twice():
    x = torch.randn(6, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(Tanh(), (x,))
    assert torch.autograd.gradgradcheck(Tanh(), (x,))  # second derivatives: Hamiltonian models' forces
    (g,) = torch.autograd.grad(Tanh()(x).sum(), x)
    assert torch.allclose(g, 1 - torch.tanh(x.detach()) ** 2)


def test_tanh_is_the_tanh_activation_and_leaves_other_devices_to_torch(monkeypatch):
    assert ACTIVATIONS["tanh"] is Tanh and isinstance(Tanh(), nn.Tanh)
    assert sum(isinstance(m, Tanh) for m in mlp(3, 8, 2)) == 2

    def refuse(x):
        raise AssertionError("the CPU path was taken off the CPU")

    monkeypatch.setattr(layers._SigmoidTanh, "apply", refuse)
    out = Tanh()(torch.empty(3, 2, device="meta"))  # torch.tanh, not 2σ(2x) − 1
    assert out.device.type == "meta" and out.shape == (3, 2)
    with pytest.raises(AssertionError, match="off the CPU"):
        Tanh()(torch.zeros(2))  # and the CPU takes it
