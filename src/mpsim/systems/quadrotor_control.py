"""The swarm's closed-loop controller: each quad tracks its reference with a geometric (SE(3)) controller at
100 Hz (zero-order hold), plus a damped least-squares feed-forward of the cable tensions the load's reference
acceleration needs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from mpsim.systems.quadrotor_dynamics import QuadrotorPlant, quat_to_rotation, rotation_to_quat, solve_sym3
from mpsim.systems.quadrotor_scenarios import DoorwayScenario, circle_directions, reference


class GeometricController:
    """Geometric tracking controller with tension feed-forward for the quads of `plant`.

    Args:
        plant: the swarm's physics (masses, gravity, inertia, rotor mixer).
        kp, kd: position and velocity gains per kg of quad.
        k_rot, k_omega: attitude and body-rate gains (per axis).
        ff_damping: ε of the damped least-squares tension feed-forward.
        rotor_max: rotor thrust bound (N); commands are clipped to [0, rotor_max].
        dither: largest sum of the per-rotor sinusoidal input dither (N) added after the mixer; 0 = off.
    """

    def __init__(
        self,
        plant: QuadrotorPlant,
        kp: float,
        kd: float,
        k_rot: Sequence[float],
        k_omega: Sequence[float],
        ff_damping: float,
        rotor_max: float,
        dither: float,
    ) -> None:
        self.plant = plant
        self.kp, self.kd = float(kp), float(kd)
        self.k_rot = torch.tensor(tuple(float(v) for v in k_rot), dtype=torch.float64)  # [3]
        self.k_omega = torch.tensor(tuple(float(v) for v in k_omega), dtype=torch.float64)  # [3]
        self.ff_damping, self.rotor_max, self.dither = float(ff_damping), float(rotor_max), float(dither)

    def feed_forward(
        self,
        n_ref: torch.Tensor,  # [B, N, 3] reference cable directions
        a_load: torch.Tensor,  # [B, 3] load reference acceleration
    ) -> torch.Tensor:
        """[B, N] tensions T ≥ 0 that best give the load its reference acceleration (damped least squares).

        The damping ε matters: in the coplanar fan MᵀM is nearly singular and the exact solve gives huge or
        negative tensions as soon as the cables leave the plane, which slackens them.
        """
        # (MᵀM + εI)⁻¹ Mᵀ w = Mᵀ (M Mᵀ + εI)⁻¹ w: a 3×3 solve whatever N is
        outer = n_ref.transpose(-1, -2) @ n_ref + self.ff_damping * self.plant.eye3  # [B, 3, 3] M Mᵀ + εI
        y = solve_sym3(outer, self.plant.load_mass * (a_load - self.plant.g))  # [B, 3], w = m_L (a_L − g)
        return (n_ref * y[:, None]).sum(-1).clamp_min(0.0)

    @staticmethod
    def attitude(force: torch.Tensor) -> torch.Tensor:  # force: [..., 3] desired thrust vector
        """[..., 3, 3] R_d = [b1 b2 b3] with b3 along the desired thrust and zero yaw (b1c = x̂)."""
        b3 = force / force.norm(dim=-1, keepdim=True)
        b1c = torch.zeros_like(b3)
        b1c[..., 0] = 1.0
        b2 = torch.linalg.cross(b3, b1c, dim=-1)
        b2 = b2 / b2.norm(dim=-1, keepdim=True)
        b1 = torch.linalg.cross(b2, b3, dim=-1)
        return torch.stack([b1, b2, b3], dim=-1)

    def trim_attitude(self, n_circ: torch.Tensor) -> torch.Tensor:  # n_circ: [B, N, 3] circle cable directions
        """[B, N, 4] the attitudes the controller commands at t = 0 in the circle (zero reference velocity and
        acceleration): a scenario's initial state starts from them, so the first command equals it."""
        a_load = n_circ.new_zeros(n_circ.shape[0], 3)  # [B, 3]
        f_des = -self.plant.quad_mass * self.plant.g + self.feed_forward(n_circ, a_load)[..., None] * n_circ
        return rotation_to_quat(self.attitude(f_des))

    def hover_state(
        self,
        load_position: torch.Tensor,  # [B, 3] load position
        r_config: torch.Tensor,  # [B] circle radius (m)
        phi: torch.Tensor,  # [B] formation yaw (rad)
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Exact static trim in the circle formation: every T_i = m_L g/(N cos α), level yaw, equal rotors.

        Returns:
            x [B, N, 13], load [B, 6] and the trim thrusts u [B, N, 4].
        """
        n_circ = circle_directions(self.plant.n_quads, self.plant.cable_length, r_config, phi)  # [B, N, 3]
        cos_alpha = n_circ[..., 2:3]
        tension = self.plant.load_mass * self.plant.gravity / (self.plant.n_quads * cos_alpha)  # [B, N, 1]
        force = -self.plant.quad_mass * self.plant.g + tension * n_circ  # thrust that cancels gravity and the cable
        q = rotation_to_quat(self.attitude(force))
        zeros = torch.zeros_like(n_circ)
        x = torch.cat([load_position[:, None] + self.plant.cable_length * n_circ, q, zeros, zeros], dim=-1)
        u = (force.norm(dim=-1, keepdim=True) / 4).expand(-1, -1, 4).contiguous()
        return x, torch.cat([load_position, torch.zeros_like(load_position)], dim=-1), u

    def control(
        self,
        x: torch.Tensor,  # [B, N, 13] quad states
        load: torch.Tensor,  # [B, 6] load state
        scenario: DoorwayScenario,
        t: float,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Geometric (SE(3)) tracking controller with tension feed-forward, plus the optional dither.

        Returns:
            the applied rotor thrusts u [B, N, 4], clipped to [0, rotor_max], and [B] whether any rotor of
            the trajectory had to be clipped (saturated).
        """
        p_ref, v_ref, a_ref, n_ref, a_load = reference(scenario, t, self.plant.cable_length)
        p, q, v, w = x[..., 0:3], x[..., 3:7], x[..., 7:10], x[..., 10:13]
        d = p - load[:, None, 0:3]
        n_meas = d / d.norm(dim=-1, keepdim=True)
        # Feed forward the *reference* tension along the *measured* cable: feeding back the measured tension
        # would turn the internal-force modes into integrators that drift until a cable slackens.
        t_ff = self.feed_forward(n_ref, a_load)  # [B, N]
        f_des = self.plant.quad_mass * (a_ref - self.plant.g + self.kp * (p_ref - p) + self.kd * (v_ref - v))
        f_des = f_des + t_ff[..., None] * n_meas
        r_des = self.attitude(f_des)  # [B, N, 3, 3]
        rot = quat_to_rotation(q)
        thrust = (f_des * rot[..., 2]).sum(-1, keepdim=True)  # F_des · R e3
        e = r_des.transpose(-1, -2) @ rot
        e = e - e.transpose(-1, -2)
        e_rot = 0.5 * torch.stack([e[..., 2, 1], e[..., 0, 2], e[..., 1, 0]], dim=-1)  # ½ vee(R_dᵀR − RᵀR_d)
        tau = -self.k_rot * e_rot - self.k_omega * w + torch.linalg.cross(w, self.plant.J * w, dim=-1)
        u = torch.cat([thrust, tau], dim=-1) @ self.plant.mixer  # [B, N, 4]
        if self.dither > 0:
            amp, freq, phase = scenario.dither.unbind(-1)  # [B, N, 4, K]
            u = u + (amp * torch.sin(2 * math.pi * freq * t + phase)).sum(-1)
        saturated = ((u < 0) | (u > self.rotor_max)).flatten(1).any(-1)
        return u.clamp(0.0, self.rotor_max), saturated
