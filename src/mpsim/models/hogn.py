"""HOGN: a graph network that outputs one scalar Hamiltonian per sample; the dynamics follow from Hamilton's
equations by autograd and are integrated with classical RK4 (Sanchez-Gonzalez et al. 2019; Martinkus et al.,
AAAI 2021, §2.2 and Appendix B).

    H_b = decode(φu(Σ_{i ∈ b} φv(V_i, Σ_{j→i} e_ji), Σ_{edges of b} e)),   V_i = (m_i, [q_i,] p_i),  p = m q̇
    dq/dt = ∂H/∂p,   dp/dt = -∂H/∂q

The sums in the global block run over each *sample's* nodes and edges (segment sums), so a batch of B
samples has B independent Hamiltonians; the reference summed over the whole collated batch, coupling the
samples of a batch through one nonlinear H (spec §7.1). On the hierarchy, the cell features (Σm, [Σq,]
centre of mass, total momentum Σp) are recomputed from the particle state inside every RK4 stage with the
stage-0 assignment, so H is a differentiable function of (q, p) alone; the reference took the lowest-level
cell positions from stage 0 without gradient (spec §7.8). Cell charge is always the total (spec §7.2). The
same graph serves all four RK4 stages (paper, Appendix B).

Because it integrates an ODE, HOGN runs at any time step, unlike DeltaGN.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import nn

from mpsim.models.gn_blocks import GLOBAL, MLP, InteractionBlock, ParticleEdges, sample_sums
from mpsim.models.nbody_base import ParticleModel, wrap_state


class HOGN(ParticleModel):
    """Hamiltonian ODE graph network on a full, kNN or hierarchical particle graph.

    Args:
        state_dim, control_dim: from the data (4 and 0).
        graph: ``full``, ``knn`` or ``hierarchical``.
        k: kNN neighbours.
        depth: quadtree depth (None: round(log4 N) at run time).
        charge: particle charge as an input feature (Coulomb).
        activation: ``softplus`` (paper; ReLU's derivative is piecewise constant, so its forces would be).
        pairs_per_trajectory, energy_horizons, energy_flag, solver: see `ParticleModel`.
    """

    def __init__(
        self,
        state_dim: int = 4,
        control_dim: int = 0,
        graph: str = "full",
        k: int = 15,
        depth: int | None = None,
        charge: bool = False,
        activation: str = "softplus",
        pairs_per_trajectory: int = 4,
        energy_horizons: Sequence[int] = (20, 200),
        energy_flag: float = 0.1,
        solver: Any = None,
    ) -> None:
        super().__init__(
            state_dim, control_dim, graph, k, depth, charge, pairs_per_trajectory, energy_horizons, energy_flag, solver
        )
        self.block = InteractionBlock(self.n_feat, activation, dt_feature=False, hierarchical=graph == "hierarchical")
        width_e, width_v = self.block.edge.width, self.block.node.width
        self.glob = MLP(width_v + width_e, GLOBAL[0], GLOBAL[1], activation)  # φu over per-sample sums
        self.decode = nn.Linear(GLOBAL[0], 1)  # φdecode: global embedding -> H

    def dt_step_fixed(self) -> bool:
        return False

    # ---- the Hamiltonian ---------------------------------------------------------------------------
    def hamiltonian(
        self,
        graph: ParticleEdges,
        q: torch.Tensor,  # [P, 2] positions
        p: torch.Tensor,  # [P, 2] momenta
        mc: torch.Tensor,  # [P, 2] (mass, charge)
        box: float,
    ) -> torch.Tensor:
        """[B] one learned Hamiltonian per sample."""
        feats = self._features(mc[:, :1], mc[:, 1:2], p)
        cell_feats, cell_pos = [], []
        if graph.hierarchy is not None:
            # cell features of this stage's state with the fixed assignment: Σm, [Σq,] centre of mass, Σp
            h = graph.hierarchy.with_features(mc[:, 0], q, p / mc[:, :1], mc[:, 1] if self.charge else None)
            for c in h.cells:
                cell_feats.append(
                    self._features(
                        c.mass[:, None], None if c.charge is None else c.charge[:, None], c.mass[:, None] * c.vel
                    )
                )
                cell_pos.append(c.pos)
        nodes, edges = self.block(graph, feats, q, box, cell_feats, cell_pos)
        b = graph.n_graphs
        pooled = torch.cat([sample_sums(nodes, b), sample_sums(edges, b)], dim=-1)  # [B, 250] per-sample sums
        return self.decode(self.glob(pooled)).squeeze(-1)

    def _features(
        self,
        mass: torch.Tensor,  # [R, 1] mass (cells: Σm)
        charge: torch.Tensor | None,  # [R, 1] charge (cells: Σq) or None
        momentum: torch.Tensor,  # [R, 2] momentum (cells: Σp)
    ) -> torch.Tensor:
        """[R, d] (m, [q,] px, py): the non-position node features."""
        cols = [mass] + ([charge if charge is not None else torch.zeros_like(mass)] if self.charge else []) + [momentum]
        return torch.cat(cols, dim=-1)

    def vector_field(
        self,
        graph: ParticleEdges,
        q: torch.Tensor,  # [P, 2] positions
        p: torch.Tensor,  # [P, 2] momenta
        mc: torch.Tensor,  # [P, 2] (mass, charge)
        box: float,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(dq/dt, dp/dt) = (∂H/∂p, -∂H/∂q), each [P, 2].

        While training the derivatives keep their graph (the loss differentiates through them); in evaluation
        each stage starts from detached leaves, so memory does not grow along the rollout.
        """
        training = self.training and torch.is_grad_enabled()
        with torch.enable_grad():
            if not training:
                q, p = q.detach().requires_grad_(True), p.detach().requires_grad_(True)
            elif not q.requires_grad:
                q, p = q.requires_grad_(True), p.requires_grad_(True)
            h = self.hamiltonian(graph, q, p, mc, box)
            # samples are independent, so the gradient of Σ_b H_b gives every sample its own ∂H_b
            dh_dq, dh_dp = torch.autograd.grad(h.sum(), (q, p), create_graph=training)
        return dh_dp, -dh_dq

    # ---- integration -------------------------------------------------------------------------------
    def advance_in_graph_order(
        self,
        x: torch.Tensor,  # [B, N, 4] states, in graph order
        nf: torch.Tensor,  # [B, N, 2] (mass, charge), in graph order
        graph: ParticleEdges,  # the graph of `x`, used by all four stages
        box: float,
        dt: float,
    ) -> torch.Tensor:
        """[B, N, 4] one classical RK4 step of Hamilton's equations (velocities = p / m), in graph order."""
        b, n, _ = x.shape
        mc = nf.reshape(-1, 2)
        m = mc[:, :1]
        q0 = x[..., :2].reshape(-1, 2)
        p0 = m * x[..., 2:].reshape(-1, 2)

        def f(q: torch.Tensor, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            return self.vector_field(graph, q, p, mc, box)

        k1q, k1p = f(q0, p0)
        k2q, k2p = f(q0 + 0.5 * dt * k1q, p0 + 0.5 * dt * k1p)
        k3q, k3p = f(q0 + 0.5 * dt * k2q, p0 + 0.5 * dt * k2p)
        k4q, k4p = f(q0 + dt * k3q, p0 + dt * k3p)
        q1 = q0 + (dt / 6.0) * (k1q + 2 * k2q + 2 * k3q + k4q)
        p1 = p0 + (dt / 6.0) * (k1p + 2 * k2p + 2 * k3p + k4p)
        out = torch.cat([q1, p1 / m], dim=-1).reshape(b, n, 4)
        return wrap_state(out, box)

    def energy_of(
        self,
        x: torch.Tensor,  # [B, N, 4] states
        node_features: torch.Tensor,  # [B, N, 2] (mass, charge)
        box: float,
    ) -> torch.Tensor:
        """[B] the learned Hamiltonian of each state, on the graph built from that state."""
        nf = node_features.to(x).expand(x.shape[0], x.shape[1], -1)
        graph = self.build_graph(x[..., :2], nf, x[..., 2:], box)
        x, nf = graph.to_graph_order(x), graph.to_graph_order(nf)  # H is a sum over particles: order-free
        mc = nf.reshape(-1, 2)
        return self.hamiltonian(graph, x[..., :2].reshape(-1, 2), mc[:, :1] * x[..., 2:].reshape(-1, 2), mc, box)
