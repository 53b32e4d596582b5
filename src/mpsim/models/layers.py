"""The building blocks every learnable model shares: one activation table, one Glorot dense layer, one stack
of linear layers, and one MLP builder.

Initialisation follows each model's reference: MPNODE.jl and the L2S baseline use Flux's default (Glorot-uniform
weights, zero biases; `dense`, `mlp`), the graph-network blocks of the N-body models keep torch's own
(`linear_stack`, see `gn_blocks.MLP`).
"""

from __future__ import annotations

from collections.abc import Sequence

from torch import nn

ACTIVATIONS: dict[str, type[nn.Module]] = {
    "tanh": nn.Tanh,
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
