"""The building blocks every learnable model shares: one activation table, one Glorot dense layer, one stack
of linear layers, and one MLP builder.

Initialisation follows each model's reference: MPNODE.jl and the L2S baseline use Flux's default (Glorot-uniform
weights, zero biases; `dense`, `mlp`), the graph-network blocks of the N-body models keep torch's own
(`linear_stack`, see `gn_blocks.MLP`).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn


class _SigmoidTanh(torch.autograd.Function):
    """tanh(x) = 2σ(2x) − 1, with tanh's own backward 1 − y² from the output."""

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:  # x: [...] any shape
        y = torch.sigmoid(x * 2).mul_(2).sub_(1)
        ctx.save_for_backward(y)
        return y

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:  # grad: [...] as x
        (y,) = ctx.saved_tensors
        return torch.ops.aten.tanh_backward(grad, y)


class Tanh(nn.Tanh):
    """nn.Tanh, computed on the CPU as 2σ(2x) − 1: torch's CPU tanh kernel is 3–4× slower than its sigmoid
    (forward and backward of a [8192, 32] float32 activation, one thread: 0.89 ms against 0.32), and tanh is the
    MP-NODE paper's activation, evaluated twice per vector-field call. The same function to rounding (at most
    2e-7 from tanh in float32, where torch's own is 3e-8 off); differentiable twice (tanh_backward has its own
    derivative); on other devices torch's tanh as is."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # x: [...] any shape
        if x.device.type != "cpu":
            return torch.tanh(x)
        return _SigmoidTanh.apply(x)


ACTIVATIONS: dict[str, type[nn.Module]] = {
    "tanh": Tanh,
    "relu": nn.ReLU,
    "softplus": nn.Softplus,
    "silu": nn.SiLU,
    "gelu": nn.GELU,
}


def activation(name: str) -> nn.Module:
    """The activation module called `name` (one of `ACTIVATIONS`)."""
    if name not in ACTIVATIONS:
        raise ValueError(f"unknown activation {name!r}; choose one of {sorted(ACTIVATIONS)}.")
    return ACTIVATIONS[name]()


def glorot_(layer: nn.Linear) -> nn.Linear:
    """Flux's default initialisation, in place: Glorot-uniform weights, zero bias."""
    nn.init.xavier_uniform_(layer.weight)
    nn.init.zeros_(layer.bias)
    return layer


def dense(n_in: int, n_out: int) -> nn.Linear:
    """A linear layer with Flux's default initialisation (Glorot-uniform weights, zero bias)."""
    return glorot_(nn.Linear(n_in, n_out))


def linear_stack(sizes: Sequence[int]) -> list[nn.Linear]:
    """Linear layers sizes[0]→sizes[1]→…→sizes[-1], with torch's default initialisation."""
    return [nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:], strict=True)]


def mlp(n_in: int, hidden: int, n_out: int, n_hidden_layers: int = 2, activation: str = "tanh") -> nn.Sequential:
    """Dense(in→h, act) → (n_hidden_layers − 1)×Dense(h→h, act) → Dense(h→out), Glorot weights, zero biases."""
    act = ACTIVATIONS[activation]
    linears = linear_stack([n_in] + [hidden] * n_hidden_layers + [n_out])
    layers: list[nn.Module] = []
    for layer in linears[:-1]:
        layers += [layer, act()]
    layers.append(linears[-1])
    for layer in linears:  # after every layer is built, as Flux (and so the seeded reference weights) does
        glorot_(layer)
    return nn.Sequential(*layers)


def output_layer(net: nn.Sequential) -> nn.Linear:
    """The last Linear of an `mlp` (indexing a Sequential is typed as a plain Module)."""
    layer = net[-1]
    assert isinstance(layer, nn.Linear), f"expected an mlp ending in a Linear layer; got {type(layer).__name__}"
    return layer
