"""N Lorenz systems with MPNODE.jl's linear all-to-all coupling.

Each node follows ẋ = σ(y − x), ẏ = x(ρ − z) − y, ż = xy − βz. The whole state, interleaved as
X = [x1, y1, z1, x2, ...] ∈ R^{3N}, evolves as Ẋ = F(X) + H·X where H is a dense 3N×3N matrix with
U[0, 1) entries, every 3×3 diagonal block set to zero (no self-coupling) and, for N > 1, scaled to
Frobenius norm c (c = 0.01 weak, 1 medium, 5 strong). H is drawn from our own seed (Julia's stream
cannot be reproduced) and stored with every dataset. The coupling is cross-component and heterogeneous
per pair, so a mean over neighbours can only approximate it; at c = 0.01 it is very weak.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch

from mpsim.errors import ConfigError
from mpsim.graphs.topology import complete
from mpsim.systems.base import System


def lorenz_coupling(n_nodes: int, strength: float, seed: int) -> torch.Tensor:
    """[3N, 3N] float64 coupling matrix H (zero 3×3 diagonal blocks, ‖H‖_F = strength for N > 1)."""
    h = torch.rand(3 * n_nodes, 3 * n_nodes, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    block = torch.arange(3 * n_nodes) // 3
    h[block[:, None] == block[None, :]] = 0.0
    if n_nodes == 1:
        return torch.zeros_like(h)
    return strength * h / torch.linalg.norm(h)


class CoupledLorenz(System):
    """Coupled Lorenz systems; node state (x, y, z).

    Args:
        name: dataset/checkpoint name.
        n_nodes: number of Lorenz systems (graph: complete, no self-loops).
        coupling: Frobenius norm c of the coupling matrix H.
        sigma, rho, beta: Lorenz parameters.
        coupling_seed: seed of H's random entries.
        ic_range: uniform range of every initial coordinate.
        effects: extra terms added to the dynamics.
    """

    state_names = ("x", "y", "z")
    dt = 0.05
    horizon = 50

    def __init__(
        self,
        name: str = "lorenz3",
        n_nodes: int = 3,
        coupling: float = 0.01,
        sigma: float = 10.0,
        rho: float = 28.0,
        beta: float = 8.0 / 3.0,
        coupling_seed: int = 42,
        ic_range: Sequence[float] = (-1.0, 1.0),
        effects: Sequence[Any] = (),
    ) -> None:
        if n_nodes < 1:
            raise ConfigError(f"system.n_nodes must be >= 1; got {n_nodes}.")
        super().__init__(name, n_nodes, complete(n_nodes), effects)
        self.coupling, self.coupling_seed = float(coupling), int(coupling_seed)
        self.sigma, self.rho, self.beta = float(sigma), float(rho), float(beta)
        self.ic_range = tuple(float(v) for v in ic_range)
        # unit-norm pattern; the strength multiplies it in `dynamics` so that it can be a learnable parameter
        self.H_unit = lorenz_coupling(n_nodes, 1.0, self.coupling_seed)  # [3N, 3N]

    @property
    def H(self) -> torch.Tensor:
        """[3N, 3N] the coupling matrix, Frobenius norm `coupling`."""
        return self.coupling * self.H_unit

    def params(self) -> dict[str, Any]:
        return {
            "n_nodes": self.n_nodes,
            "coupling": self.coupling,
            "coupling_seed": self.coupling_seed,
            "sigma": self.sigma,
            "rho": self.rho,
            "beta": self.beta,
            "ic_range": list(self.ic_range),
            "H": self.H.tolist(),
        }

    def dynamics(
        self,
        t: torch.Tensor,  # [] time
        x: torch.Tensor,  # [B, N, 3] (x, y, z)
        u: torch.Tensor | None = None,  # unused: no controls
    ) -> torch.Tensor:
        a, b, c = x[..., 0], x[..., 1], x[..., 2]
        own = torch.stack([self.sigma * (b - a), a * (self.rho - c) - b, a * b - self.beta * c], dim=-1)
        if self.n_nodes == 1:
            return own
        flat = x.reshape(*x.shape[:-2], 3 * self.n_nodes)
        return own + self.coupling * (flat @ self.H_unit.to(x).T).reshape(x.shape)

    def sample_initial_states(self, n: int, generator: torch.Generator) -> torch.Tensor:
        lo, hi = self.ic_range
        return lo + (hi - lo) * torch.rand(n, self.n_nodes, 3, generator=generator, dtype=torch.float64)
