"""Equations of motion of N quadrotors carrying a point-mass load on rigid cables (no controller, no scenario).

Quad i has the node state ``[p(3), q(4) (w, x, y, z), v(3), ω(3)]`` (p, v in the world frame, ω in the body
frame) and the node control ``u_i = [F1..F4]``, rotor thrusts in N ("+" layout, rotor 1 at +x, 2 at +y, 3 at −x,
4 at −y). The load is a point mass ``[p_L, v_L]``. With ``n_i = (p_i − p_L)/ℓ_i``:

    ṗ_i = v_i,  q̇_i = ½ q_i ⊗ [0, ω_i],  v̇_i = g + (R_i f_i e3 − T_i n_i)/m_q,  ω̇_i = J⁻¹(τ_i − ω_i × Jω_i)
    ṗ_L = v_L,  v̇_L = g + Σ_j T_j n_j / m_L

Cables are massless, rigid and unilateral. The tensions T are Lagrange multipliers solved at every
right-hand-side evaluation from ``c̈ + 2ζω_b ċ + ω_b² c = 0`` on ``c_i = ½(ℓ_i² − L²)`` (Baumgarte), an SPD
N×N system for any geometry, solved in O(N) through the load's 3 degrees of freedom (Woodbury).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch


def quat_to_rotation(q: torch.Tensor) -> torch.Tensor:  # q: [..., 4] unit quaternion (w, x, y, z)
    """[..., 3, 3] rotation matrix (body → world) of a scalar-first unit quaternion."""
    w, x, y, z = q.unbind(-1)
    rows = (
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    )  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(*q.shape[:-1], 3, 3)


def rotation_to_quat(r: torch.Tensor) -> torch.Tensor:  # r: [..., 3, 3] rotation matrices
    """[..., 4] scalar-first quaternion with w > 0 (valid for rotation angles below 180°, i.e. any tilt here)."""
    w = 0.5 * torch.sqrt((1 + r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2]).clamp_min(1e-12))
    x = (r[..., 2, 1] - r[..., 1, 2]) / (4 * w)
    y = (r[..., 0, 2] - r[..., 2, 0]) / (4 * w)
    z = (r[..., 1, 0] - r[..., 0, 1]) / (4 * w)
    return torch.stack([w, x, y, z], dim=-1)


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:  # a, b: [..., 4] (w, x, y, z)
    """[..., 4] Hamilton product a ⊗ b."""
    aw, av = a[..., :1], a[..., 1:]
    bw, bv = b[..., :1], b[..., 1:]
    w = aw * bw - (av * bv).sum(-1, keepdim=True)
    return torch.cat([w, aw * bv + bw * av + torch.linalg.cross(av, bv, dim=-1)], dim=-1)


def solve_sym3(m: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:  # m: [..., 3, 3] SPD, rhs: [..., 3]
    """[..., 3] m⁻¹ rhs by the adjugate formula: branch-free and LAPACK-free.

    Batched LAPACK on tiny matrices costs milliseconds per call (and far more when threads are oversubscribed),
    more than the whole rest of the right-hand side; every 3×3 matrix solved here is well conditioned.
    """
    a, b, c = m.unbind(-2)
    bc, ca, ab = (
        torch.linalg.cross(b, c, dim=-1),
        torch.linalg.cross(c, a, dim=-1),
        torch.linalg.cross(a, b, dim=-1),
    )
    det = (a * bc).sum(-1, keepdim=True)
    return (rhs[..., 0:1] * bc + rhs[..., 1:2] * ca + rhs[..., 2:3] * ab) / det


class Derivatives(NamedTuple):
    """Right-hand side of the whole swarm (quads and load) at one state."""

    dx: torch.Tensor  # [..., N, 13] quad state derivative
    dload: torch.Tensor  # [..., 6] load state derivative
    tension: torch.Tensor  # [..., N] cable tensions (N)
    power: torch.Tensor  # [...] power of thrusts and rotor torques Σ_i (R_i f_i e3·v_i + τ_i·ω_i) (W)


class QuadrotorPlant:
    """The swarm's physics: right-hand side with the cable tensions, a fixed-step RK4 step, mechanical energy.

    Args:
        n_quads: number of quadrotors N.
        quad_mass, load_mass, inertia, arm, torque_coeff, cable_length, gravity: m_q, m_L, diag(J), l_a, k_m, L, g
            (SI units).
        baumgarte: (ω_b, ζ) of the cable-constraint stabilisation.
    """

    def __init__(
        self,
        n_quads: int,
        quad_mass: float,
        load_mass: float,
        inertia: Sequence[float],
        arm: float,
        torque_coeff: float,
        cable_length: float,
        gravity: float,
        baumgarte: Sequence[float],
    ) -> None:
        self.n_quads = int(n_quads)
        self.quad_mass, self.load_mass = float(quad_mass), float(load_mass)
        self.cable_length, self.gravity = float(cable_length), float(gravity)
        self.baumgarte = tuple(float(v) for v in baumgarte)
        f64 = torch.float64
        self.g = torch.tensor([0.0, 0.0, -self.gravity], dtype=f64)  # [3] gravity vector
        self.J = torch.tensor(tuple(float(v) for v in inertia), dtype=f64)  # [3] diag(J)
        la, km = float(arm), float(torque_coeff)
        # rotor thrusts → (f, τx, τy, τz) for the "+" layout: τ = [l_a(F2−F4), l_a(F3−F1), k_m(F1−F2+F3−F4)]
        self.wrench = torch.tensor(
            [[1.0, 0.0, -la, km], [1.0, la, 0.0, -km], [1.0, 0.0, la, km], [1.0, -la, 0.0, -km]], dtype=f64
        )  # [4 rotors, 4]: wrench = u @ wrench
        self.mixer = torch.linalg.inv(self.wrench)  # [4, 4]: u = wrench @ mixer
        self.eye3 = torch.eye(3, dtype=f64)  # [3, 3]

    def derivatives(
        self,
        x: torch.Tensor,  # [..., N, 13] quad states
        load: torch.Tensor,  # [..., 6] load position and velocity
        u: torch.Tensor,  # [..., N, 4] rotor thrusts (N)
    ) -> Derivatives:
        """Time derivatives of quads and load, with the cable tensions that keep every cable at length L."""
        p, q, v, w = x[..., 0:3], x[..., 3:7], x[..., 7:10], x[..., 10:13]
        p_load, v_load = load[..., None, 0:3], load[..., None, 3:6]
        wrench = u @ self.wrench  # [..., N, 4] (f, τ)
        w_, x_, y_, z_ = q.unbind(-1)
        thrust_axis = torch.stack(  # R e3: the rotors push along the body z axis
            [2 * (x_ * z_ + w_ * y_), 2 * (y_ * z_ - w_ * x_), 1 - 2 * (x_ * x_ + y_ * y_)], dim=-1
        )
        force = wrench[..., :1] * thrust_axis  # [..., N, 3]
        tau = wrench[..., 1:]  # [..., N, 3]

        d = p - p_load  # [..., N, 3] load → quad
        ell = d.norm(dim=-1)  # [..., N]
        n = d / ell[..., None]
        dv = v - v_load
        c_dot = (d * dv).sum(-1)
        c = 0.5 * (ell * ell - self.cable_length**2)
        omega_b, zeta = self.baumgarte
        # Rigid cables: choose T so that c̈ + 2ζω_b ċ + ω_b² c = 0 for c = ½(ℓ² − L²). This is A T = b with
        # A = I/m_q + U Uᵀ/m_L (U = [n_1 … n_N]ᵀ), SPD even when all cables lie in one plane (the doorway fan).
        b = (n * force).sum(-1) / self.quad_mass + (
            (dv * dv).sum(-1) + 2 * zeta * omega_b * c_dot + omega_b**2 * c
        ) / ell  # [..., N]
        # The cables interact only through the load's 3 translational degrees of freedom, so by Woodbury
        # A⁻¹ b = m_q (b − U S⁻¹ Uᵀ b) with the 3×3 S = (m_L/m_q) I + UᵀU (eigenvalues ≥ m_L/m_q): O(N), no N×N solve.
        s = self.eye3 * (self.load_mass / self.quad_mass) + n.transpose(-1, -2) @ n  # [..., 3, 3]
        y = solve_sym3(s, (n * b[..., None]).sum(-2))  # [..., 3] S⁻¹ Uᵀ b
        tension = self.quad_mass * (b - (n * y[..., None, :]).sum(-1))  # [..., N]
        pull = tension[..., None] * n  # [..., N, 3] force of cable i on the load (its reaction acts on quad i)

        acc = self.g + (force - pull) / self.quad_mass
        acc_load = self.g + pull.sum(-2) / self.load_mass
        # q̇ = ½ q ⊗ [0, ω] with ω in the body frame
        q_dot = 0.5 * torch.cat(
            [
                -(q[..., 1:] * w).sum(-1, keepdim=True),
                q[..., :1] * w + torch.linalg.cross(q[..., 1:], w, dim=-1),
            ],
            dim=-1,
        )
        w_dot = (tau - torch.linalg.cross(w, self.J * w, dim=-1)) / self.J
        power = (force * v).sum((-1, -2)) + (tau * w).sum((-1, -2))  # tensions do no work on rigid cables
        dx = torch.cat([v, q_dot, acc, w_dot], dim=-1)
        return Derivatives(dx, torch.cat([load[..., 3:6], acc_load], dim=-1), tension, power)

    def step(
        self,
        x: torch.Tensor,  # [..., N, 13] quad states
        load: torch.Tensor,  # [..., 6] load state
        u: torch.Tensor,  # [..., N, 4] rotor thrusts, held over the step
        h: float,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """One RK4 step of length h; quaternions renormalised after it.

        Returns:
            x [..., N, 13] and load [..., 6] after the step, the tensions [..., N] at its start, and the input
            work [...] over it (RK4 quadrature of `Derivatives.power`, for the energy balance).
        """
        k1 = self.derivatives(x, load, u)
        k2 = self.derivatives(x.add(k1.dx, alpha=0.5 * h), load.add(k1.dload, alpha=0.5 * h), u)
        k3 = self.derivatives(x.add(k2.dx, alpha=0.5 * h), load.add(k2.dload, alpha=0.5 * h), u)
        k4 = self.derivatives(x.add(k3.dx, alpha=h), load.add(k3.dload, alpha=h), u)
        x = x.add(k1.dx.add(k2.dx + k3.dx, alpha=2).add(k4.dx), alpha=h / 6)
        load = load.add(k1.dload.add(k2.dload + k3.dload, alpha=2).add(k4.dload), alpha=h / 6)
        q = x[..., 3:7] / x[..., 3:7].norm(dim=-1, keepdim=True)
        x = torch.cat([x[..., :3], q, x[..., 7:]], dim=-1)
        work = (h / 6) * (k1.power + 2 * k2.power + 2 * k3.power + k4.power)
        return x, load, k1.tension, work

    def mechanical_energy(
        self,
        x: torch.Tensor,  # [..., N, 13] quad states
        load: torch.Tensor,  # [..., 6] load state
    ) -> torch.Tensor:
        """[...] kinetic + potential energy of quads and load (changes only by the rotors' work)."""
        v, w = x[..., 7:10], x[..., 10:13]
        quads = 0.5 * self.quad_mass * (v * v).sum(-1) + 0.5 * (self.J * w * w).sum(-1)
        quads = quads + self.quad_mass * self.gravity * x[..., 2]
        v_load = load[..., 3:6]
        load_e = 0.5 * self.load_mass * (v_load * v_load).sum(-1) + self.load_mass * self.gravity * load[..., 2]
        return quads.sum(-1) + load_e
