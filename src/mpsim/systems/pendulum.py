"""N identical pendulums whose bobs are coupled by horizontal springs on any undirected graph.

Each pendulum (mass m, length l, gravity g) hangs from a fixed pivot; the pivots are level and a spring of
stiffness k joins the bobs of neighbouring pendulums i ~ j, acting on their horizontal displacement
l·sin θ. With A the (symmetric) adjacency matrix, the Lagrangian gives

    θ̈_i = −(g/l)·sin θ_i − (k/m)·cos θ_i · Σ_j A_ij (sin θ_i − sin θ_j)

and the energy, conserved exactly by the flow,

    E = Σ_i [ ½ m l² θ̇_i² + m g l (1 − cos θ_i) ] + ½ k l² Σ_{i<j} A_ij (sin θ_i − sin θ_j)².

For small angles this is the textbook pair −(g/l)θ_i − (k/m)(θ_i − θ_j) that the MP-NODE paper's
"pendulums connected by a string" reduces to. Unlike MPNODE.jl's equation (which divides by cos θ), it is
regular for every angle, so the paper's initial range θ ∈ [−π/2, π/2], θ̇ ∈ [−1, 1] is safe.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch

from mpsim.errors import ConfigError
from mpsim.graphs.topology import make_topology
from mpsim.systems.base import System


class CoupledPendulums(System):
    """Spring-coupled pendulums; node state (θ, θ̇).

    Args:
        name: dataset/checkpoint name.
        n_nodes: number of pendulums.
        graph: coupling topology (``complete``, ``chain``, ``ring``, ``grid``, ...); must be undirected.
        mass, length, spring, gravity: m, l, k, g (SI units).
        theta_range, omega_range: uniform ranges of the initial angle (rad) and angular velocity (rad/s).
        effects: extra terms added to the dynamics (e.g. hidden damping to make a test dataset).
    """

    state_names = ("theta", "omega")
    dt = 0.1
    horizon = 50

    def __init__(
        self,
        name: str = "pendulum2",
        n_nodes: int = 2,
        graph: str = "complete",
        mass: float = 1.0,
        length: float = 1.5,
        spring: float = 2.0,
        gravity: float = 9.81,
        theta_range: Sequence[float] = (-math.pi / 2, math.pi / 2),
        omega_range: Sequence[float] = (-1.0, 1.0),
        effects: Sequence[Any] = (),
    ) -> None:
        if n_nodes < 1:
            raise ConfigError(f"system.n_nodes must be >= 1; got {n_nodes}.")
        if mass <= 0 or length <= 0:
            raise ConfigError(f"system.mass and system.length must be > 0; got {mass}, {length}.")
        edge_index = make_topology(graph, n_nodes) if n_nodes > 1 else torch.zeros(2, 0, dtype=torch.long)
        a = torch.zeros(n_nodes, n_nodes)
        a[edge_index[1], edge_index[0]] = 1.0
        if not torch.equal(a, a.T):
            raise ConfigError(f"pendulum springs need an undirected graph; graph={graph!r} is directed.")
        super().__init__(name, n_nodes, edge_index, effects)
        self.graph = graph
        self.mass, self.length, self.spring, self.gravity = float(mass), float(length), float(spring), float(gravity)
        self.theta_range = tuple(float(v) for v in theta_range)
        self.omega_range = tuple(float(v) for v in omega_range)

    def params(self) -> dict[str, Any]:
        return {
            "n_nodes": self.n_nodes,
            "graph": self.graph,
            "mass": self.mass,
            "length": self.length,
            "spring": self.spring,
            "gravity": self.gravity,
            "theta_range": list(self.theta_range),
            "omega_range": list(self.omega_range),
        }

    def _spring_sum(self, s: torch.Tensor) -> torch.Tensor:  # s: [B, N] sin θ
        """[B, N] Σ_j A_ij (s_i − s_j) over each pendulum's neighbours."""
        src, dst = self.edge_index.to(s.device)
        neighbour_sum = torch.zeros_like(s).index_add_(1, dst, s[:, src])
        degree = torch.zeros(s.shape[1], dtype=s.dtype, device=s.device).index_add_(
            0, dst, torch.ones_like(dst, dtype=s.dtype)
        )
        return degree * s - neighbour_sum

    def dynamics(
        self,
        t: torch.Tensor,  # [] time
        x: torch.Tensor,  # [B, N, 2] (θ, θ̇)
        u: torch.Tensor | None = None,  # unused: no controls
    ) -> torch.Tensor:
        theta, omega = x[..., 0], x[..., 1]
        s = torch.sin(theta)
        accel = -(self.gravity / self.length) * s - (self.spring / self.mass) * torch.cos(theta) * self._spring_sum(s)
        return torch.stack([omega, accel], dim=-1)

    def energy(
        self,
        x: torch.Tensor,  # [..., N, 2] (θ, θ̇)
        node_features: torch.Tensor | None = None,  # unused: identical pendulums
    ) -> torch.Tensor:
        theta, omega = x[..., 0], x[..., 1]
        m, l, k, g = self.mass, self.length, self.spring, self.gravity
        kinetic = 0.5 * m * l**2 * omega.pow(2).sum(-1)
        gravity = (m * g * l * (1 - torch.cos(theta))).sum(-1)
        s = torch.sin(theta)
        src, dst = self.edge_index.to(x.device)
        # each undirected edge appears twice in edge_index: ½·½ Σ over directed edges
        springs = 0.25 * k * l**2 * (s[..., src] - s[..., dst]).pow(2).sum(-1)
        return kinetic + gravity + springs

    def sample_initial_states(self, n: int, generator: torch.Generator) -> torch.Tensor:
        r = torch.rand(n, self.n_nodes, 2, generator=generator, dtype=torch.float64)
        lo = torch.tensor([self.theta_range[0], self.omega_range[0]], dtype=torch.float64)
        hi = torch.tensor([self.theta_range[1], self.omega_range[1]], dtype=torch.float64)
        return lo + (hi - lo) * r
