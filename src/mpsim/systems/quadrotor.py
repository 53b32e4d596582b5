"""A swarm of N quadrotors carrying a cable-suspended point-mass load through a doorway (MP-NODE's quad3/quad6).

MP-NODE's own generator is not public; this follows our spec (`shared/reference/quadrotor_spec.md`), whose
physical and door parameters come from Jackson et al., RA-L 2020.

Bodies. Quad i has the node state ``[p(3), q(4) (w, x, y, z), v(3), ω(3)]`` (p, v in the world frame, ω in
the body frame) and the node control ``u_i = [F1..F4]``, rotor thrusts in N ("+" layout, rotor 1 at +x,
2 at +y, 3 at −x, 4 at −y). The load is a point mass ``[p_L, v_L]``; it is not a node (it is not
homogeneous with the quads) and is returned beside the node data. With ``n_i = (p_i − p_L)/ℓ_i``:

    ṗ_i = v_i,  q̇_i = ½ q_i ⊗ [0, ω_i],  v̇_i = g + (R_i f_i e3 − T_i n_i)/m_q,  ω̇_i = J⁻¹(τ_i − ω_i × Jω_i)
    ṗ_L = v_L,  v̇_L = g + Σ_j T_j n_j / m_L

Cables are massless, rigid and unilateral. The tensions T are Lagrange multipliers solved at every
right-hand-side evaluation from ``c̈ + 2ζω_b ċ + ω_b² c = 0`` on ``c_i = ½(ℓ_i² − L²)`` (Baumgarte), an SPD
N×N system for any geometry, solved in O(N) through the load's 3 degrees of freedom (Woodbury). A trajectory
whose tension drops below ``min_tension`` (a slack cable, which this model cannot represent) is rejected and
resampled.

Closed loop. A reference moves the load through the door in three min-jerk phases (align and morph the
quads from a circle into a single-file "fan" in the x-z plane, traverse, morph back) and each quad tracks
``p_L^ref + L n_i(s)`` with a geometric (SE(3)) controller at 100 Hz (zero-order hold), plus a damped
least-squares tension feed-forward. The plant is integrated with fixed-step RK4 within each hold.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from typing import Any, NamedTuple

import torch

from mpsim.data.trajectories import Trajectories
from mpsim.errors import ConfigError, IncompatibleError
from mpsim.graphs.topology import complete
from mpsim.systems.base import System

# Door of Jackson et al.: vertical cylinders (radius 0.5 m) at x ∈ {2.5, 3.0}, y = ±0.85, leaving 0.7 m.
DOOR_CENTRES = ((2.5, 0.85), (2.5, -0.85), (3.0, 0.85), (3.0, -0.85))
DOOR_RADIUS = 0.5
QUAD_RADIUS = 0.275  # physical collision radii (Jackson's ×1.25 inflation is a planning margin, not used)
LOAD_RADIUS = 0.2
CEILING = 2.1
TRAVERSE_END_X = 5.5  # the load's x at the end of the single-file traverse (well past the door)
SETTLE_TIME = 1.0  # a run this long past the manoeuvre's end must have the load at its goal


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


def _quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:  # a, b: [..., 4] (w, x, y, z)
    """[..., 4] Hamilton product a ⊗ b."""
    aw, av = a[..., :1], a[..., 1:]
    bw, bv = b[..., :1], b[..., 1:]
    w = aw * bw - (av * bv).sum(-1, keepdim=True)
    return torch.cat([w, aw * bv + bw * av + torch.linalg.cross(av, bv, dim=-1)], dim=-1)


def _solve_sym3(m: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:  # m: [..., 3, 3] SPD, rhs: [..., 3]
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


def _min_jerk(t: float, t0: torch.Tensor, dur: torch.Tensor) -> tuple[torch.Tensor, ...]:  # t0, dur: [...]
    """Min-jerk blend h(σ) = 10σ³ − 15σ⁴ + 6σ⁵, σ = (t − t0)/dur clipped to [0, 1], and its time derivatives.

    h' and h'' vanish at σ = 0 and 1, so clipping σ makes the blend exactly flat outside its window.
    """
    sig = ((t - t0) / dur).clamp(0.0, 1.0)
    one = 1.0 - sig
    h = sig * sig * sig * (10.0 - 15.0 * sig + 6.0 * sig * sig)
    return h, 30.0 * sig * sig * one * one / dur, 60.0 * sig * one * (1.0 - 2.0 * sig) / (dur * dur)


class Derivatives(NamedTuple):
    """Right-hand side of the whole swarm (quads and load) at one state."""

    dx: torch.Tensor  # [..., N, 13] quad state derivative
    dload: torch.Tensor  # [..., 6] load state derivative
    tension: torch.Tensor  # [..., N] cable tensions (N)
    power: torch.Tensor  # [...] power of thrusts and rotor torques Σ_i (R_i f_i e3·v_i + τ_i·ω_i) (W)


@dataclass
class DoorwayScenario:
    """Per-trajectory random scenario: reference segments, formations and initial state (leading axis B).

    The load reference and the morph variable s are sums of min-jerk moves: for columns (x, y, z, s),
    ``value(t) = start + Σ_k delta_k h((t − t0_k)/dur_k)`` over the three phases k.
    """

    start: torch.Tensor  # [B, 4] (x, y, z) of the load at t = 0, and s = 0
    goal: torch.Tensor  # [B, 3] load goal
    seg_t0: torch.Tensor  # [B, 3, 4] start time of each phase's move, per column
    seg_dur: torch.Tensor  # [B, 3, 4] its duration
    seg_delta: torch.Tensor  # [B, 3, 4] its displacement
    n_circ: torch.Tensor  # [B, N, 3] cable directions (load → quad) in the circle formation
    n_fan: torch.Tensor  # [B, N, 3] cable directions in the doorway fan
    durations: torch.Tensor  # [B, 3] phase durations T1, T2, T3 (s)
    z_door: torch.Tensor  # [B] load height through the door
    r_config: torch.Tensor  # [B] circle radius (m)
    beta: torch.Tensor  # [B] fan half-angle (rad)
    x0: torch.Tensor  # [B, N, 13] initial quad states
    load0: torch.Tensor  # [B, 6] initial load state
    dither: torch.Tensor  # [B, N, 4, K, 3] per-rotor sinusoids (amplitude N, frequency Hz, phase rad)

    def __len__(self) -> int:
        return self.start.shape[0]

    def subset(self, index: torch.Tensor) -> DoorwayScenario:  # index: [k] trajectory indices
        return replace(self, **{f.name: getattr(self, f.name)[index] for f in fields(self)})

    @staticmethod
    def concat(parts: Sequence[DoorwayScenario]) -> DoorwayScenario:
        return DoorwayScenario(**{f.name: torch.cat([getattr(p, f.name) for p in parts]) for f in fields(parts[0])})


@dataclass
class SwarmRollout:
    """A closed-loop simulation: node data plus the load, tensions, scenario and per-trajectory checks.

    Attributes:
        trajectories: node states x [B, T, N, 13] and applied rotor thrusts u [B, T, N, 4].
        load: [B, T, 6] load position and velocity at the sample times.
        tension: [B, T, N] cable tensions at the sample times.
        scenario: the scenarios that were flown.
        checks: name → [B] worst value over every 100 Hz tick (tensions over every RK4 step) of the spec's
            bounds: ``min_tension``, ``min_height_gap`` (z_i − z_L), ``min_quad_distance``,
            ``min_door_clearance_quad``, ``min_door_clearance_load``, ``max_z``, ``min_z``,
            ``saturated_ticks``, ``max_cable_error``, ``min_qw``, ``goal_error`` (NaN when the run ends
            before the manoeuvre has settled).
        accepted: [B] every bound held.
    """

    trajectories: Trajectories
    load: torch.Tensor
    tension: torch.Tensor
    scenario: DoorwayScenario
    checks: dict[str, torch.Tensor]
    accepted: torch.Tensor

    def subset(self, index: torch.Tensor) -> SwarmRollout:  # index: [k] trajectory indices
        return SwarmRollout(
            trajectories=self.trajectories.subset(index),
            load=self.load[index],
            tension=self.tension[index],
            scenario=self.scenario.subset(index),
            checks={k: v[index] for k, v in self.checks.items()},
            accepted=self.accepted[index],
        )

    @staticmethod
    def concat(parts: Sequence[SwarmRollout]) -> SwarmRollout:
        return SwarmRollout(
            trajectories=Trajectories.concat([p.trajectories for p in parts]),
            load=torch.cat([p.load for p in parts]),
            tension=torch.cat([p.tension for p in parts]),
            scenario=DoorwayScenario.concat([p.scenario for p in parts]),
            checks={k: torch.cat([p.checks[k] for p in parts]) for k in parts[0].checks},
            accepted=torch.cat([p.accepted for p in parts]),
        )


class QuadrotorSwarm(System):
    """N quadrotors carrying a point-mass load on rigid cables through a doorway; node = one quadrotor.

    Data are closed-loop: `generate` samples random scenarios, flies them with the built-in controller,
    rejects trajectories that break a bound (slack cable, collision, saturation, ...) and resamples them.
    x holds only the quads; the load, tensions and scenarios come from `generate_full`.

    Args:
        name: dataset/checkpoint name (``quad3``, ``quad6``).
        n_quads: number of quadrotors N (graph: complete, no self-loops: all couple through the load).
        dt: sampling step of the data, a multiple of `control_dt`.
        horizon: samples per trajectory after t = 0 (the default 15 s covers the longest manoeuvre, 14 s,
            plus a 1 s settle).
        control_dt: controller period (zero-order hold of the rotor thrusts).
        substeps: RK4 steps per control period.
        quad_mass, load_mass, inertia, arm, torque_coeff, cable_length, gravity: m_q, m_L, diag(J), l_a,
            k_m, L, g (SI units).
        rotor_max: rotor thrust bound (N); None gives (m_q + m_L) g / 4, at which one quad only just holds
            the load.
        baumgarte: (ω_b, ζ) of the cable-constraint stabilisation.
        min_tension: tension below which a cable counts as slack and its trajectory is rejected (N).
        kp, kd: position and velocity gains per kg of quad.
        k_rot, k_omega: attitude and body-rate gains (per axis).
        ff_damping: ε of the damped least-squares tension feed-forward.
        fan_half_angle: range of the fan half-angle β in degrees; None gives [40, 50] for N ≤ 3 and
            [b, b + 5] with b = (N − 1)·asin(0.35/L) otherwise, so that neighbours keep 0.7 m apart.
        r_config_range, z_door_range: ranges of the circle radius and of the load height in the door.
        phase_ranges: ranges of the three phase durations T1, T2, T3 (s).
        attitude_noise: largest initial attitude perturbation (degrees, random axis).
        velocity_noise: largest initial velocity per axis (m/s), equal on all bodies (keeps ċ = 0).
        dither: largest sum of the per-rotor sinusoidal input dither (N), added after the mixer; 0 = off.
        u_sampling: ``mean`` records each sample's u as the mean applied thrust over the following dt (the
            best zero-order hold), ``first`` as the thrust applied at the sample time; equal at dt = control_dt.
        max_rounds: resampling rounds before `generate` gives up on a scenario range that keeps failing.
        threads: torch intra-op threads while flying (restored after); None keeps torch's setting. The
            tensors are small, so extra threads gain little, and on a shared 2-core machine two threads made
            a 1000-trajectory batch 4× slower than one.
        effects: not supported (the data are closed-loop); must be empty.
    """

    state_names = ("px", "py", "pz", "qw", "qx", "qy", "qz", "vx", "vy", "vz", "wx", "wy", "wz")
    control_names = ("f1", "f2", "f3", "f4")
    dt = 0.05
    horizon = 300

    def __init__(
        self,
        name: str = "quad3",
        n_quads: int = 3,
        dt: float = 0.05,
        horizon: int = 300,
        control_dt: float = 0.01,
        substeps: int = 5,
        quad_mass: float = 1.0,
        load_mass: float = 0.9,
        inertia: Sequence[float] = (0.0023, 0.0023, 0.004),
        arm: float = 0.175,
        torque_coeff: float = 0.0245,
        cable_length: float = 1.55,
        gravity: float = 9.81,
        rotor_max: float | None = None,
        baumgarte: Sequence[float] = (20.0, 1.0),
        min_tension: float = 0.1,
        kp: float = 4.0,
        kd: float = 3.6,
        k_rot: Sequence[float] = (0.92, 0.92, 0.4),
        k_omega: Sequence[float] = (0.092, 0.092, 0.08),
        ff_damping: float = 0.05,
        fan_half_angle: Sequence[float] | None = None,
        r_config_range: Sequence[float] = (1.0, 1.3),
        z_door_range: Sequence[float] = (0.25, 0.45),
        phase_ranges: Sequence[Sequence[float]] = ((2.5, 3.5), (5.0, 7.0), (2.5, 3.5)),
        attitude_noise: float = 2.0,
        velocity_noise: float = 0.0,
        dither: float = 0.0,
        u_sampling: str = "mean",
        max_rounds: int = 10,
        threads: int | None = 1,
        effects: Sequence[Any] = (),
    ) -> None:
        if n_quads < 1:
            raise ConfigError(f"system.n_quads must be >= 1; got {n_quads}.")
        if effects:
            raise ConfigError("system=quadrotor does not take effects (its data are closed-loop); set effects=[].")
        if u_sampling not in ("mean", "first"):
            raise ConfigError(f"system.u_sampling must be 'mean' or 'first'; got {u_sampling!r}.")
        if control_dt <= 0 or substeps < 1:
            raise ConfigError(f"need control_dt > 0 and substeps >= 1; got {control_dt}, {substeps}.")
        super().__init__(name, n_quads, complete(n_quads), effects)
        self.dt, self.horizon = float(dt), int(horizon)
        self.control_dt, self.substeps = float(control_dt), int(substeps)
        self.quad_mass, self.load_mass = float(quad_mass), float(load_mass)
        self.inertia = tuple(float(v) for v in inertia)
        self.arm, self.torque_coeff = float(arm), float(torque_coeff)
        self.cable_length, self.gravity = float(cable_length), float(gravity)
        self.rotor_max = (self.quad_mass + self.load_mass) * self.gravity / 4 if rotor_max is None else float(rotor_max)
        self.baumgarte = tuple(float(v) for v in baumgarte)
        self.min_tension = float(min_tension)
        self.kp, self.kd = float(kp), float(kd)
        self.k_rot, self.k_omega = tuple(float(v) for v in k_rot), tuple(float(v) for v in k_omega)
        self.ff_damping = float(ff_damping)
        if fan_half_angle is None:
            if self.n_nodes <= 3:
                fan_half_angle = (40.0, 50.0)
            else:
                # neighbouring fan slots are 2L·sin(β/(N−1)) apart: keep that ≥ 0.7 m (> 2 quad radii)
                low = (self.n_nodes - 1) * math.degrees(math.asin(0.35 / self.cable_length))
                fan_half_angle = (low, low + 5.0)
        self.fan_half_angle = tuple(float(v) for v in fan_half_angle)
        self.r_config_range = tuple(float(v) for v in r_config_range)
        self.z_door_range = tuple(float(v) for v in z_door_range)
        self.phase_ranges = tuple(tuple(float(v) for v in r) for r in phase_ranges)
        self.attitude_noise, self.velocity_noise = float(attitude_noise), float(velocity_noise)
        self.dither = float(dither)
        self.u_sampling, self.max_rounds = u_sampling, int(max_rounds)
        self.threads = None if threads is None else int(threads)
        if not 0 < self.r_config_range[0] <= self.r_config_range[1] < self.cable_length:
            raise ConfigError(
                f"system.r_config_range must lie in (0, cable_length={self.cable_length}); got {self.r_config_range}."
            )

        f64 = torch.float64
        self._g = torch.tensor([0.0, 0.0, -self.gravity], dtype=f64)  # [3]
        self._J = torch.tensor(self.inertia, dtype=f64)  # [3]
        self._k_rot = torch.tensor(self.k_rot, dtype=f64)  # [3]
        self._k_omega = torch.tensor(self.k_omega, dtype=f64)  # [3]
        la, km = self.arm, self.torque_coeff
        # rotor thrusts → (f, τx, τy, τz) for the "+" layout: τ = [l_a(F2−F4), l_a(F3−F1), k_m(F1−F2+F3−F4)]
        self._wrench = torch.tensor(
            [[1.0, 0.0, -la, km], [1.0, la, 0.0, -km], [1.0, 0.0, la, km], [1.0, -la, 0.0, -km]], dtype=f64
        )  # [4 rotors, 4]: wrench = u @ _wrench
        self._mixer = torch.linalg.inv(self._wrench)  # [4, 4]: u = wrench @ _mixer
        self._door = torch.tensor(DOOR_CENTRES, dtype=f64)  # [4, 2]
        self._eye = torch.eye(self.n_nodes, dtype=f64)  # [N, N]
        self._eye3 = torch.eye(3, dtype=f64)  # [3, 3]

    # ---- facts ---------------------------------------------------------------------------------------

    def params(self) -> dict[str, Any]:
        return {
            "n_quads": self.n_nodes,
            "control_dt": self.control_dt,
            "substeps": self.substeps,
            "quad_mass": self.quad_mass,
            "load_mass": self.load_mass,
            "inertia": list(self.inertia),
            "arm": self.arm,
            "torque_coeff": self.torque_coeff,
            "cable_length": self.cable_length,
            "gravity": self.gravity,
            "rotor_max": self.rotor_max,
            "baumgarte": list(self.baumgarte),
            "min_tension": self.min_tension,
            "kp": self.kp,
            "kd": self.kd,
            "k_rot": list(self.k_rot),
            "k_omega": list(self.k_omega),
            "ff_damping": self.ff_damping,
            "fan_half_angle": list(self.fan_half_angle),
            "r_config_range": list(self.r_config_range),
            "z_door_range": list(self.z_door_range),
            "phase_ranges": [list(r) for r in self.phase_ranges],
            "attitude_noise": self.attitude_noise,
            "velocity_noise": self.velocity_noise,
            "dither": self.dither,
            "u_sampling": self.u_sampling,
            "door_centres": [list(c) for c in DOOR_CENTRES],
            "door_radius": DOOR_RADIUS,
            "quad_radius": QUAD_RADIUS,
            "load_radius": LOAD_RADIUS,
            "ceiling": CEILING,
        }

    # ---- plant ---------------------------------------------------------------------------------------
    def dynamics(
        self,
        t: torch.Tensor,  # [] time
        x: torch.Tensor,  # [B, N, 13] quad states
        u: torch.Tensor | None = None,  # [B, N, 4] rotor thrusts
    ) -> torch.Tensor:
        raise IncompatibleError(
            "QuadrotorSwarm couples its quads through the load, whose state is not part of x [B, N, 13]; "
            "call `derivatives(x, load, u)` (or `step`) with the load state, e.g. from `generate_full`."
        )

    def derivatives(
        self,
        x: torch.Tensor,  # [..., N, 13] quad states
        load: torch.Tensor,  # [..., 6] load position and velocity
        u: torch.Tensor,  # [..., N, 4] rotor thrusts (N)
    ) -> Derivatives:
        """Time derivatives of quads and load, with the cable tensions that keep every cable at length L."""
        p, q, v, w = x[..., 0:3], x[..., 3:7], x[..., 7:10], x[..., 10:13]
        p_load, v_load = load[..., None, 0:3], load[..., None, 3:6]
        wrench = u @ self._wrench  # [..., N, 4] (f, τ)
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
        s = self._eye3 * (self.load_mass / self.quad_mass) + n.transpose(-1, -2) @ n  # [..., 3, 3]
        y = _solve_sym3(s, (n * b[..., None]).sum(-2))  # [..., 3] S⁻¹ Uᵀ b
        tension = self.quad_mass * (b - (n * y[..., None, :]).sum(-1))  # [..., N]
        pull = tension[..., None] * n  # [..., N, 3] force of cable i on the load (its reaction acts on quad i)

        acc = self._g + (force - pull) / self.quad_mass
        acc_load = self._g + pull.sum(-2) / self.load_mass
        # q̇ = ½ q ⊗ [0, ω] with ω in the body frame
        q_dot = 0.5 * torch.cat(
            [
                -(q[..., 1:] * w).sum(-1, keepdim=True),
                q[..., :1] * w + torch.linalg.cross(q[..., 1:], w, dim=-1),
            ],
            dim=-1,
        )
        w_dot = (tau - torch.linalg.cross(w, self._J * w, dim=-1)) / self._J
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
        quads = 0.5 * self.quad_mass * (v * v).sum(-1) + 0.5 * (self._J * w * w).sum(-1)
        quads = quads + self.quad_mass * self.gravity * x[..., 2]
        v_load = load[..., 3:6]
        load_e = 0.5 * self.load_mass * (v_load * v_load).sum(-1) + self.load_mass * self.gravity * load[..., 2]
        return quads.sum(-1) + load_e

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
        n_circ = self._circle(r_config, phi)  # [B, N, 3]
        cos_alpha = n_circ[..., 2:3]
        tension = self.load_mass * self.gravity / (self.n_nodes * cos_alpha)  # [B, N, 1]
        force = -self.quad_mass * self._g + tension * n_circ  # thrust that cancels gravity and the cable
        q = rotation_to_quat(self._attitude(force))
        zeros = torch.zeros_like(n_circ)
        x = torch.cat([load_position[:, None] + self.cable_length * n_circ, q, zeros, zeros], dim=-1)
        u = (force.norm(dim=-1, keepdim=True) / 4).expand(-1, -1, 4).contiguous()
        return x, torch.cat([load_position, torch.zeros_like(load_position)], dim=-1), u

    # ---- scenario and reference ----------------------------------------------------------------------
    def _circle(self, r_config: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:  # [B], [B]
        """[B, N, 3] cable directions with the quads evenly on a circle of radius r_config around the load."""
        sin_a = r_config / self.cable_length
        cos_a = torch.sqrt(1 - sin_a * sin_a)
        theta = phi[:, None] + 2 * math.pi * torch.arange(self.n_nodes, dtype=torch.float64) / self.n_nodes  # [B, N]
        sin_a = sin_a[:, None]
        return torch.stack(
            [sin_a * torch.cos(theta), sin_a * torch.sin(theta), cos_a[:, None].expand_as(theta)], dim=-1
        )

    def sample_scenarios(self, n: int, generator: torch.Generator) -> DoorwayScenario:
        """`n` random doorway scenarios (spec §5) with their trim initial states, drawn with `generator`."""
        f64, N = torch.float64, self.n_nodes

        def uniform(lo: float, hi: float, *shape: int) -> torch.Tensor:
            return lo + (hi - lo) * torch.rand(n, *shape, generator=generator, dtype=f64)

        start = torch.stack([uniform(-0.5, 0.0), uniform(-0.75, 0.75), uniform(0.25, 0.6)], dim=-1)  # [n, 3]
        goal = torch.stack([uniform(5.8, 6.5), uniform(-0.75, 0.75), uniform(0.25, 0.6)], dim=-1)
        z_door = uniform(*self.z_door_range)
        r_config = uniform(*self.r_config_range)
        phi = uniform(0.0, 2 * math.pi / N)
        beta = torch.deg2rad(uniform(*self.fan_half_angle))
        durations = torch.stack([uniform(*r) for r in self.phase_ranges], dim=-1)  # [n, 3]

        n_circ = self._circle(r_config, phi)
        # Fan slots ψ ∈ linspace(−β, β) go to the quads in order of their circle x-offset, front (largest x,
        # ψ = −β) to back, so that their paths do not cross during the morph.
        rank = torch.argsort(torch.argsort(-n_circ[..., 0], dim=1), dim=1).to(f64)  # [n, N]
        psi = -beta[:, None] + 2 * beta[:, None] * rank / max(N - 1, 1) if N > 1 else torch.zeros(n, 1, dtype=f64)
        n_fan = torch.stack([-torch.sin(psi), torch.zeros_like(psi), torch.cos(psi)], dim=-1)

        t1, t2, t3 = durations.unbind(-1)
        t12, zero, one = t1 + t2, torch.zeros_like(t1), torch.ones_like(t1)
        x0, y0, z0 = start.unbind(-1)
        # Phases (columns x, y, z, s): 1) creep x by 0.2 m, bring y to 0 and z to the door height over 0.8·T1,
        # morph circle → fan over [0.35·T1, T1] (lateral moves happen while the circle still locks the load);
        # 2) traverse in the fan to x = 5.5; 3) morph back over 0.8·T3, go to the goal (y, z over [0.2, 1]·T3).
        seg_t0 = torch.stack([
            torch.stack([zero, zero, zero, 0.35 * t1], -1),
            torch.stack([t1, t1, t1, t1], -1),
            torch.stack([t12, t12 + 0.2 * t3, t12 + 0.2 * t3, t12], -1),
        ], dim=1)  # fmt: skip
        seg_dur = torch.stack([
            torch.stack([t1, 0.8 * t1, 0.8 * t1, 0.65 * t1], -1),
            torch.stack([t2, t2, t2, t2], -1),
            torch.stack([t3, 0.8 * t3, 0.8 * t3, 0.8 * t3], -1),
        ], dim=1)  # fmt: skip
        seg_delta = torch.stack([
            torch.stack([0.2 * one, -y0, z_door - z0, one], -1),
            torch.stack([TRAVERSE_END_X - x0 - 0.2, zero, zero, zero], -1),
            torch.stack([goal[:, 0] - TRAVERSE_END_X, goal[:, 1], goal[:, 2] - z_door, -one], -1),
        ], dim=1)  # fmt: skip

        # Initial state: trim of the controller at t = 0 (zero reference velocity and acceleration), so the
        # first command equals the initial attitude; then small random attitude and common velocity offsets.
        f_des = -self.quad_mass * self._g + self._feed_forward(n_circ, torch.zeros_like(start))[..., None] * n_circ
        q = rotation_to_quat(self._attitude(f_des))  # [n, N, 4]
        axis = torch.randn(n, N, 3, generator=generator, dtype=f64)
        half = 0.5 * math.radians(self.attitude_noise) * (2 * torch.rand(n, N, 1, generator=generator, dtype=f64) - 1)
        dq = torch.cat([torch.cos(half), torch.sin(half) * axis / axis.norm(dim=-1, keepdim=True)], dim=-1)
        q = _quat_mul(q, dq)
        vel = uniform(-self.velocity_noise, self.velocity_noise, 3)  # [n, 3], the same on every body
        p_load = start
        x0_quads = torch.cat(
            [
                p_load[:, None] + self.cable_length * n_circ,
                q,
                vel[:, None].expand(-1, N, -1),
                torch.zeros_like(n_circ),
            ],
            dim=-1,
        )
        load0 = torch.cat([p_load, vel], dim=-1)

        # Input dither: 3 sinusoids per rotor, 0.5–5 Hz, amplitudes summing to at most `dither`.
        k = 3
        dither = torch.stack(
            [
                uniform(0.0, self.dither / k, N, 4, k),
                uniform(0.5, 5.0, N, 4, k),
                uniform(0.0, 2 * math.pi, N, 4, k),
            ],
            dim=-1,
        )
        return DoorwayScenario(
            start=torch.cat([start, zero[:, None]], dim=-1),
            goal=goal,
            seg_t0=seg_t0,
            seg_dur=seg_dur,
            seg_delta=seg_delta,
            n_circ=n_circ,
            n_fan=n_fan,
            durations=durations,
            z_door=z_door,
            r_config=r_config,
            beta=beta,
            x0=x0_quads,
            load0=load0,
            dither=dither,
        )

    def sample_initial_states(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """[n, N, 13] initial quad states of `n` random scenarios (use `sample_scenarios` to fly them)."""
        return self.sample_scenarios(n, generator).x0

    def reference(
        self, scenario: DoorwayScenario, t: float
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Reference at time t (analytic derivatives of the min-jerk blends and of the morph).

        Returns:
            quad position, velocity, acceleration [B, N, 3], reference cable directions n_ref [B, N, 3] and
            load reference acceleration [B, 3].
        """
        h, h_dot, h_ddot = _min_jerk(t, scenario.seg_t0, scenario.seg_dur)  # [B, 3, 4]
        pos = scenario.start + (scenario.seg_delta * h).sum(1)  # [B, 4]
        vel = (scenario.seg_delta * h_dot).sum(1)
        acc = (scenario.seg_delta * h_ddot).sum(1)
        s, s_dot, s_ddot = pos[:, None, 3:], vel[:, None, 3:], acc[:, None, 3:]  # [B, 1, 1]
        # Morph n(s) = m/|m|, m = (1−s) n_circ + s n_fan: |p_i − p_L| = L holds exactly along the way.
        chord = scenario.n_fan - scenario.n_circ  # dm/ds
        m = scenario.n_circ + s * chord
        r = m.norm(dim=-1, keepdim=True)
        n = m / r
        r1 = (n * chord).sum(-1, keepdim=True)  # dr/ds
        n1 = (chord - n * r1) / r  # dn/ds
        r2 = (n1 * chord).sum(-1, keepdim=True)
        n2 = (-2 * n1 * r1 - n * r2) / r  # d²n/ds²
        length = self.cable_length
        p_ref = pos[:, None, :3] + length * n
        v_ref = vel[:, None, :3] + length * n1 * s_dot
        a_ref = acc[:, None, :3] + length * (n2 * s_dot * s_dot + n1 * s_ddot)
        return p_ref, v_ref, a_ref, n, acc[:, :3]

    # ---- controller ----------------------------------------------------------------------------------
    def _feed_forward(
        self,
        n_ref: torch.Tensor,  # [B, N, 3] reference cable directions
        a_load: torch.Tensor,  # [B, 3] load reference acceleration
    ) -> torch.Tensor:
        """[B, N] tensions T ≥ 0 that best give the load its reference acceleration (damped least squares).

        The damping ε matters: in the coplanar fan MᵀM is nearly singular and the exact solve gives huge or
        negative tensions as soon as the cables leave the plane, which slackens them.
        """
        # (MᵀM + εI)⁻¹ Mᵀ w = Mᵀ (M Mᵀ + εI)⁻¹ w: a 3×3 solve whatever N is
        outer = n_ref.transpose(-1, -2) @ n_ref + self.ff_damping * self._eye3  # [B, 3, 3] M Mᵀ + εI
        y = _solve_sym3(outer, self.load_mass * (a_load - self._g))  # [B, 3], w = m_L (a_L − g)
        return (n_ref * y[:, None]).sum(-1).clamp_min(0.0)

    def _attitude(self, force: torch.Tensor) -> torch.Tensor:  # force: [..., 3] desired thrust vector
        """[..., 3, 3] R_d = [b1 b2 b3] with b3 along the desired thrust and zero yaw (b1c = x̂)."""
        b3 = force / force.norm(dim=-1, keepdim=True)
        b1c = torch.zeros_like(b3)
        b1c[..., 0] = 1.0
        b2 = torch.linalg.cross(b3, b1c, dim=-1)
        b2 = b2 / b2.norm(dim=-1, keepdim=True)
        b1 = torch.linalg.cross(b2, b3, dim=-1)
        return torch.stack([b1, b2, b3], dim=-1)

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
        p_ref, v_ref, a_ref, n_ref, a_load = self.reference(scenario, t)
        p, q, v, w = x[..., 0:3], x[..., 3:7], x[..., 7:10], x[..., 10:13]
        d = p - load[:, None, 0:3]
        n_meas = d / d.norm(dim=-1, keepdim=True)
        # Feed forward the *reference* tension along the *measured* cable: feeding back the measured tension
        # would turn the internal-force modes into integrators that drift until a cable slackens.
        t_ff = self._feed_forward(n_ref, a_load)  # [B, N]
        f_des = self.quad_mass * (a_ref - self._g + self.kp * (p_ref - p) + self.kd * (v_ref - v))
        f_des = f_des + t_ff[..., None] * n_meas
        r_des = self._attitude(f_des)  # [B, N, 3, 3]
        rot = quat_to_rotation(q)
        thrust = (f_des * rot[..., 2]).sum(-1, keepdim=True)  # F_des · R e3
        e = r_des.transpose(-1, -2) @ rot
        e = e - e.transpose(-1, -2)
        e_rot = 0.5 * torch.stack([e[..., 2, 1], e[..., 0, 2], e[..., 1, 0]], dim=-1)  # ½ vee(R_dᵀR − RᵀR_d)
        tau = -self._k_rot * e_rot - self._k_omega * w + torch.linalg.cross(w, self._J * w, dim=-1)
        u = torch.cat([thrust, tau], dim=-1) @ self._mixer  # [B, N, 4]
        if self.dither > 0:
            amp, freq, phase = scenario.dither.unbind(-1)  # [B, N, 4, K]
            u = u + (amp * torch.sin(2 * math.pi * freq * t + phase)).sum(-1)
        saturated = ((u < 0) | (u > self.rotor_max)).flatten(1).any(-1)
        return u.clamp(0.0, self.rotor_max), saturated

    # ---- data ----------------------------------------------------------------------------------------
    def _ticks_per_sample(self, dt: float) -> int:
        k = round(dt / self.control_dt)
        if k < 1 or not math.isclose(k * self.control_dt, dt, rel_tol=1e-9, abs_tol=1e-12):
            raise ConfigError(
                f"quadrotor data need dt to be a whole multiple of control_dt={self.control_dt}; got dt={dt}. "
                f"Set system.dt to e.g. {max(1, k) * self.control_dt:g}."
            )
        return k

    def rollout(self, scenario: DoorwayScenario, dt: float | None = None, horizon: int | None = None) -> SwarmRollout:
        """Fly `scenario` in closed loop from its initial state for `horizon` samples of `dt` (no rejection).

        Every 100 Hz tick the controller sets u (held for `substeps` RK4 steps) and the spec's bounds are
        checked; x and load are recorded at the sample times, u per `u_sampling`.
        """
        previous = torch.get_num_threads()
        if self.threads is not None:
            torch.set_num_threads(self.threads)
        try:
            return self._rollout(scenario, dt, horizon)
        finally:
            torch.set_num_threads(previous)

    @torch.no_grad()
    def _rollout(self, scenario: DoorwayScenario, dt: float | None, horizon: int | None) -> SwarmRollout:
        dt = self.dt if dt is None else float(dt)
        horizon = self.horizon if horizon is None else int(horizon)
        ticks = self._ticks_per_sample(dt)
        h = self.control_dt / self.substeps
        x, load = scenario.x0.clone(), scenario.load0.clone()
        b, n = x.shape[:2]
        xs = x.new_empty(b, horizon + 1, n, 13)
        loads, tensions = x.new_empty(b, horizon + 1, 6), x.new_empty(b, horizon + 1, n)
        us = x.new_empty(b, horizon + 1, n, 4)
        inf = torch.full((b,), math.inf, dtype=x.dtype)
        worst = {
            "min_tension": inf.clone(),
            "min_height_gap": inf.clone(),
            "min_quad_distance": inf.clone(),
            "min_door_clearance_quad": inf.clone(),
            "min_door_clearance_load": inf.clone(),
            "max_z": -inf,
            "min_z": inf.clone(),
            "saturated_ticks": torch.zeros(b, dtype=x.dtype),
            "max_cable_error": torch.zeros(b, dtype=x.dtype),
            "min_qw": inf.clone(),
        }
        # the extra sample interval after the last sample only supplies that sample's u
        for k in range(horizon + 1):
            xs[:, k], loads[:, k] = x, load
            u_sum = torch.zeros_like(us[:, 0])
            for j in range(ticks):
                t = (k * ticks + j) * self.control_dt
                u, saturated = self.control(x, load, scenario, t)
                worst["saturated_ticks"] += saturated.to(x.dtype)
                self._check_geometry(x, load, worst)
                u_sum = u_sum + u if self.u_sampling == "mean" or j == 0 else u_sum
                for i in range(self.substeps):
                    x, load, tension, _ = self.step(x, load, u, h)
                    worst["min_tension"] = torch.minimum(worst["min_tension"], tension.amin(-1))
                    if j == 0 and i == 0:
                        tensions[:, k] = tension
            us[:, k] = u_sum / ticks if self.u_sampling == "mean" else u_sum
        self._check_geometry(x, load, worst)
        worst["min_tension"] = torch.minimum(worst["min_tension"], self.derivatives(x, load, u).tension.amin(-1))
        # a diverged (NaN) trajectory gets the failing extreme of every check
        worst = {key: torch.nan_to_num(val, nan=-math.inf if key.startswith("min") else math.inf)
                 for key, val in worst.items()}  # fmt: skip
        settled = horizon * dt >= scenario.durations.sum(-1) + SETTLE_TIME
        goal_error = (loads[:, -1, :3] - scenario.goal).norm(dim=-1)
        worst["goal_error"] = torch.where(settled, goal_error, torch.full_like(goal_error, math.nan))
        accepted = (
            self._bounds_held(worst) & torch.isfinite(xs).flatten(1).all(-1) & torch.isfinite(us).flatten(1).all(-1)
        )
        traj = Trajectories(  # NaN zeroed so that the container validates; `accepted` is False there
            t=torch.arange(horizon + 1, dtype=torch.float64) * dt,
            x=torch.nan_to_num(xs),
            u=torch.nan_to_num(us),
            edge_index=self.edge_index,
            meta=self.meta(dt),
        )
        return SwarmRollout(traj, loads, tensions, scenario, worst, accepted)

    def _check_geometry(
        self,
        x: torch.Tensor,  # [B, N, 13] quad states
        load: torch.Tensor,  # [B, 6] load state
        worst: dict[str, torch.Tensor],  # name -> [B] running worst values, updated in place
    ) -> None:
        p, p_load = x[..., 0:3], load[:, 0:3]
        worst["min_height_gap"] = torch.minimum(worst["min_height_gap"], (p[..., 2] - p_load[:, None, 2]).amin(-1))
        if self.n_nodes > 1:
            dist = (p[:, :, None] - p[:, None]).norm(dim=-1) + 1e9 * self._eye  # ignore i = j
            worst["min_quad_distance"] = torch.minimum(worst["min_quad_distance"], dist.flatten(1).amin(-1))
        door_q = (p[..., None, :2] - self._door).norm(dim=-1).flatten(1).amin(-1) - DOOR_RADIUS - QUAD_RADIUS
        door_l = (p_load[:, None, :2] - self._door).norm(dim=-1).amin(-1) - DOOR_RADIUS - LOAD_RADIUS
        worst["min_door_clearance_quad"] = torch.minimum(worst["min_door_clearance_quad"], door_q)
        worst["min_door_clearance_load"] = torch.minimum(worst["min_door_clearance_load"], door_l)
        worst["max_z"] = torch.maximum(worst["max_z"], p[..., 2].amax(-1))
        worst["min_z"] = torch.minimum(worst["min_z"], torch.minimum(p[..., 2].amin(-1), p_load[:, 2]))
        cable = ((p - p_load[:, None]).norm(dim=-1) - self.cable_length).abs().amax(-1)
        worst["max_cable_error"] = torch.maximum(worst["max_cable_error"], cable)
        worst["min_qw"] = torch.minimum(worst["min_qw"], x[..., 3].amin(-1))

    def _bounds_held(self, worst: dict[str, torch.Tensor]) -> torch.Tensor:  # worst: name -> [B]
        """[B] the spec's §7 bounds: taut cables, load below quads, no collisions, inside the room, no saturation."""
        failures = self.failed_checks(worst)
        return ~torch.stack(list(failures.values())).any(0)

    def failed_checks(self, worst: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:  # worst: name -> [B]
        """name → [B] whether each bound failed (the reasons a trajectory is rejected)."""
        return {
            "slack_cable": ~(worst["min_tension"] > self.min_tension),
            "load_not_below": ~(worst["min_height_gap"] > 0.3),
            "quad_collision": ~(worst["min_quad_distance"] > 2 * QUAD_RADIUS),
            "door_collision": ~((worst["min_door_clearance_quad"] > 0) & (worst["min_door_clearance_load"] > 0)),
            "out_of_room": ~((worst["max_z"] <= CEILING) & (worst["min_z"] >= 0)),
            "saturation": worst["saturated_ticks"] > 0,
            "cable_length": ~(worst["max_cable_error"] < 1e-4),
            "quaternion_flip": ~(worst["min_qw"] > 0),
            "goal_missed": worst["goal_error"] >= 0.1,  # NaN (run too short to judge) counts as held
        }

    def generate_full(self, n: int, seed: int, dt: float | None = None, horizon: int | None = None) -> SwarmRollout:
        """`n` accepted closed-loop trajectories from scenarios drawn with `seed` (rejected ones resampled).

        The returned trajectories' meta records ``seed``, ``n_simulated``, ``n_rejected`` and the count of
        each failed bound under ``rejections``.

        Raises:
            ConfigError: if fewer than `n` trajectories pass after `max_rounds` rounds of resampling.
        """
        dt = self.dt if dt is None else float(dt)
        horizon = self.horizon if horizon is None else int(horizon)
        if horizon < 1 or n < 1:
            raise ConfigError(f"need horizon >= 1 and n >= 1; got horizon={horizon}, n={n}.")
        if self.n_nodes < 2:
            raise ConfigError(
                f"the doorway scenario needs n_quads >= 2 (one quad cannot lift the load); got {self.n_nodes}."
            )
        self._ticks_per_sample(dt)
        generator = torch.Generator().manual_seed(int(seed))
        parts: list[SwarmRollout] = []
        n_ok = n_simulated = n_rejected = 0
        rejections: dict[str, int] = {}
        for round_ in range(self.max_rounds):
            need = n - n_ok
            # later rounds oversample: a small batch costs about as much as a full one
            batch = need if round_ == 0 else 2 * need + 2
            run = self.rollout(self.sample_scenarios(batch, generator), dt, horizon)
            n_simulated += batch
            n_rejected += int((~run.accepted).sum())
            for reason, failed in self.failed_checks(run.checks).items():
                rejections[reason] = rejections.get(reason, 0) + int(failed.sum())
            keep = torch.nonzero(run.accepted).flatten()[:need]
            parts.append(run.subset(keep))
            n_ok += len(keep)
            if n_ok == n:
                break
        else:
            raise ConfigError(
                f"quadrotor: only {n_ok} of {n} trajectories passed the checks after {self.max_rounds} rounds "
                f"({n_rejected} of {n_simulated} rejected; failed bounds: {rejections}). Narrow the scenario "
                "ranges (system.fan_half_angle, system.phase_ranges, system.dither) or raise system.max_rounds."
            )
        out = SwarmRollout.concat(parts)
        meta = dict(out.trajectories.meta)
        meta.update(seed=int(seed), n_simulated=n_simulated, n_rejected=n_rejected, rejections=rejections)
        out.trajectories = replace(out.trajectories, meta=meta)
        return out

    def generate(
        self,
        n: int,
        seed: int,
        dt: float | None = None,
        horizon: int | None = None,
        rtol: float = 1e-8,
        atol: float = 1e-10,
    ) -> Trajectories:
        """`n` accepted trajectories (node data only; see `generate_full`). rtol/atol are unused (fixed-step RK4)."""
        return self.generate_full(n, seed, dt, horizon).trajectories

    def simulate(
        self,
        x0: torch.Tensor,  # [B, N, 13] initial quad states
        t: torch.Tensor,  # [T] output times 0, dt, 2dt, ...
        rtol: float = 1e-8,
        atol: float = 1e-10,
        method: str = "rk4",
        *,
        scenario: DoorwayScenario | None = None,
    ) -> Trajectories:
        """Fly `scenario` from `x0` (no rejection) and return the node data; rtol/atol/method are unused.

        Raises:
            ConfigError: without a scenario (the controller's reference depends on it), or if `t` is not a
                uniform grid from 0 whose step is a multiple of `control_dt`.
        """
        if scenario is None:
            raise ConfigError(
                "QuadrotorSwarm.simulate needs `scenario=` (from `sample_scenarios`): the closed loop tracks a "
                "scenario-specific reference. Use `generate(n, seed)` to sample and fly scenarios."
            )
        t = t.to(torch.float64)
        dt = float(t[1] - t[0])
        grid = torch.arange(len(t), dtype=torch.float64) * dt
        if float(t[0]) != 0.0 or not torch.allclose(t, grid, rtol=0, atol=1e-9):
            raise ConfigError("QuadrotorSwarm.simulate needs a uniform time grid starting at t = 0.")
        run = self.rollout(replace(scenario, x0=x0.to(torch.float64)), dt, len(t) - 1)
        return run.trajectories
