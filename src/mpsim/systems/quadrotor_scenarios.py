"""The doorway manoeuvre: scenarios, the reference the controller tracks, and the spec's bounds.

A reference moves the load through the door in three min-jerk phases (align and morph the quads from a circle
into a single-file "fan" in the x-z plane, traverse, morph back); each quad tracks ``p_L^ref + L n_i(s)``.
The door and room are those of Jackson et al., RA-L 2020 (`shared/reference/quadrotor_spec.md`); a flight is
accepted only when every bound of the spec's §7 held (`failed_checks`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields, replace

import torch

from mpsim.systems.quadrotor_dynamics import quat_mul

# Door of Jackson et al.: vertical cylinders (radius 0.5 m) at x ∈ {2.5, 3.0}, y = ±0.85, leaving 0.7 m.
DOOR_CENTRES = ((2.5, 0.85), (2.5, -0.85), (3.0, 0.85), (3.0, -0.85))
DOOR_RADIUS = 0.5
QUAD_RADIUS = 0.275  # physical collision radii (Jackson's ×1.25 inflation is a planning margin, not used)
LOAD_RADIUS = 0.2
CEILING = 2.1
TRAVERSE_END_X = 5.5  # the load's x at the end of the single-file traverse (well past the door)
SETTLE_TIME = 1.0  # a run this long past the manoeuvre's end must have the load at its goal


def min_jerk(t: float, t0: torch.Tensor, dur: torch.Tensor) -> tuple[torch.Tensor, ...]:  # t0, dur: [...]
    """Min-jerk blend h(σ) = 10σ³ − 15σ⁴ + 6σ⁵, σ = (t − t0)/dur clipped to [0, 1], and its time derivatives.

    h' and h'' vanish at σ = 0 and 1, so clipping σ makes the blend exactly flat outside its window.
    """
    sig = ((t - t0) / dur).clamp(0.0, 1.0)
    one = 1.0 - sig
    h = sig * sig * sig * (10.0 - 15.0 * sig + 6.0 * sig * sig)
    return h, 30.0 * sig * sig * one * one / dur, 60.0 * sig * one * (1.0 - 2.0 * sig) / (dur * dur)


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


def circle_directions(
    n_quads: int,
    cable_length: float,
    r_config: torch.Tensor,  # [B] circle radius (m)
    phi: torch.Tensor,  # [B] formation yaw (rad)
) -> torch.Tensor:
    """[B, N, 3] cable directions with the quads evenly on a circle of radius r_config around the load."""
    sin_a = r_config / cable_length
    cos_a = torch.sqrt(1 - sin_a * sin_a)
    theta = phi[:, None] + 2 * math.pi * torch.arange(n_quads, dtype=torch.float64) / n_quads  # [B, N]
    sin_a = sin_a[:, None]
    return torch.stack([sin_a * torch.cos(theta), sin_a * torch.sin(theta), cos_a[:, None].expand_as(theta)], dim=-1)


def reference(
    scenario: DoorwayScenario, t: float, cable_length: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Reference at time t (analytic derivatives of the min-jerk blends and of the morph).

    Returns:
        quad position, velocity, acceleration [B, N, 3], reference cable directions n_ref [B, N, 3] and
        load reference acceleration [B, 3].
    """
    h, h_dot, h_ddot = min_jerk(t, scenario.seg_t0, scenario.seg_dur)  # [B, 3, 4]
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
    p_ref = pos[:, None, :3] + cable_length * n
    v_ref = vel[:, None, :3] + cable_length * n1 * s_dot
    a_ref = acc[:, None, :3] + cable_length * (n2 * s_dot * s_dot + n1 * s_ddot)
    return p_ref, v_ref, a_ref, n, acc[:, :3]


@dataclass(frozen=True)
class DoorwayScenarios:
    """The distribution of doorway scenarios (spec §5) for `n_quads` quads on cables of `cable_length` m.

    Attributes:
        fan_half_angle: range of the fan half-angle β in degrees.
        r_config_range, z_door_range: ranges of the circle radius and of the load height in the door.
        phase_ranges: ranges of the three phase durations T1, T2, T3 (s).
        attitude_noise: largest initial attitude perturbation (degrees, random axis).
        velocity_noise: largest initial velocity per axis (m/s), equal on all bodies (keeps ċ = 0).
        dither: largest sum of the per-rotor sinusoidal input dither (N); 0 = off.
    """

    n_quads: int
    cable_length: float
    fan_half_angle: tuple[float, ...]
    r_config_range: tuple[float, ...]
    z_door_range: tuple[float, ...]
    phase_ranges: tuple[tuple[float, ...], ...]
    attitude_noise: float
    velocity_noise: float
    dither: float

    def sample(
        self, n: int, generator: torch.Generator, trim_attitude: Callable[[torch.Tensor], torch.Tensor]
    ) -> DoorwayScenario:
        """`n` random scenarios with their initial states, drawn with `generator`; `trim_attitude` maps the
        circle's cable directions [n, N, 3] to the controller's trim attitudes [n, N, 4] at t = 0."""
        f64, N = torch.float64, self.n_quads

        def uniform(lo: float, hi: float, *shape: int) -> torch.Tensor:
            return lo + (hi - lo) * torch.rand(n, *shape, generator=generator, dtype=f64)

        def in_range(bounds: tuple[float, ...]) -> torch.Tensor:  # [n] from a (lo, hi) range
            lo, hi = bounds
            return uniform(lo, hi)

        start = torch.stack([uniform(-0.5, 0.0), uniform(-0.75, 0.75), uniform(0.25, 0.6)], dim=-1)  # [n, 3]
        goal = torch.stack([uniform(5.8, 6.5), uniform(-0.75, 0.75), uniform(0.25, 0.6)], dim=-1)
        z_door = in_range(self.z_door_range)
        r_config = in_range(self.r_config_range)
        phi = uniform(0.0, 2 * math.pi / N)
        beta = torch.deg2rad(in_range(self.fan_half_angle))
        durations = torch.stack([in_range(r) for r in self.phase_ranges], dim=-1)  # [n, 3]
        n_circ = circle_directions(self.n_quads, self.cable_length, r_config, phi)
        seg_t0, seg_dur, seg_delta = _segments(start, goal, z_door, durations)

        # Initial state: trim of the controller at t = 0 (zero reference velocity and acceleration), so the
        # first command equals the initial attitude; then small random attitude and common velocity offsets.
        q = trim_attitude(n_circ)  # [n, N, 4]
        axis = torch.randn(n, N, 3, generator=generator, dtype=f64)
        half = 0.5 * math.radians(self.attitude_noise) * (2 * torch.rand(n, N, 1, generator=generator, dtype=f64) - 1)
        dq = torch.cat([torch.cos(half), torch.sin(half) * axis / axis.norm(dim=-1, keepdim=True)], dim=-1)
        vel = uniform(-self.velocity_noise, self.velocity_noise, 3)  # [n, 3], the same on every body
        position = start[:, None] + self.cable_length * n_circ  # [n, N, 3]
        x0 = torch.cat([position, quat_mul(q, dq), vel[:, None].expand(-1, N, -1), torch.zeros_like(n_circ)], dim=-1)
        # Input dither: 3 sinusoids per rotor, 0.5–5 Hz, amplitudes summing to at most `dither`.
        k = 3
        dither = [
            uniform(0.0, self.dither / k, N, 4, k),
            uniform(0.5, 5.0, N, 4, k),
            uniform(0.0, 2 * math.pi, N, 4, k),
        ]
        return DoorwayScenario(
            start=torch.cat([start, torch.zeros_like(start[:, :1])], dim=-1),
            goal=goal,
            seg_t0=seg_t0,
            seg_dur=seg_dur,
            seg_delta=seg_delta,
            n_circ=n_circ,
            n_fan=fan_directions(n_circ, beta),
            durations=durations,
            z_door=z_door,
            r_config=r_config,
            beta=beta,
            x0=x0,
            load0=torch.cat([start, vel], dim=-1),
            dither=torch.stack(dither, dim=-1),
        )


def fan_directions(
    n_circ: torch.Tensor,  # [B, N, 3] cable directions in the circle formation
    beta: torch.Tensor,  # [B] fan half-angle (rad)
) -> torch.Tensor:  # [B, N, 3] cable directions in the doorway fan
    """The fan in the x-z plane: slots ψ ∈ linspace(−β, β) go to the quads in order of their circle x-offset,
    front (largest x, ψ = −β) to back, so that their paths do not cross during the morph."""
    b, n = n_circ.shape[:2]
    rank = torch.argsort(torch.argsort(-n_circ[..., 0], dim=1), dim=1).to(torch.float64)  # [B, N]
    psi = -beta[:, None] + 2 * beta[:, None] * rank / max(n - 1, 1) if n > 1 else torch.zeros(b, 1, dtype=torch.float64)
    return torch.stack([-torch.sin(psi), torch.zeros_like(psi), torch.cos(psi)], dim=-1)


def _segments(
    start: torch.Tensor,  # [B, 3] load position at t = 0
    goal: torch.Tensor,  # [B, 3] load goal
    z_door: torch.Tensor,  # [B] load height through the door
    durations: torch.Tensor,  # [B, 3] phase durations T1, T2, T3
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # [B, 3, 4] each: t0, duration, displacement
    """The three phases' min-jerk moves of columns (x, y, z, s), as `DoorwayScenario.seg_*`.

    1) creep x by 0.2 m, bring y to 0 and z to the door height over 0.8·T1, morph circle → fan over
    [0.35·T1, T1] (lateral moves happen while the circle still locks the load); 2) traverse in the fan to
    x = 5.5; 3) morph back over 0.8·T3, go to the goal (y, z over [0.2, 1]·T3).
    """
    t1, t2, t3 = durations.unbind(-1)
    t12, zero, one = t1 + t2, torch.zeros_like(t1), torch.ones_like(t1)
    x0, y0, z0 = start.unbind(-1)
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
    return seg_t0, seg_dur, seg_delta


def update_checks(
    worst: dict[str, torch.Tensor],  # name -> [B] running worst values, updated in place
    x: torch.Tensor,  # [B, N, 13] quad states
    load: torch.Tensor,  # [B, 6] load state
    cable_length: float,
) -> None:
    """Fold the geometric bounds at one instant (height gap, quad distances, door clearances, room, cable length,
    quaternion sign) into the running worst values (see `SwarmRollout.checks`)."""
    door = torch.tensor(DOOR_CENTRES, dtype=x.dtype)  # [4, 2]
    p, p_load = x[..., 0:3], load[:, 0:3]
    worst["min_height_gap"] = torch.minimum(worst["min_height_gap"], (p[..., 2] - p_load[:, None, 2]).amin(-1))
    if x.shape[1] > 1:
        dist = (p[:, :, None] - p[:, None]).norm(dim=-1) + 1e9 * torch.eye(x.shape[1], dtype=x.dtype)  # ignore i = j
        worst["min_quad_distance"] = torch.minimum(worst["min_quad_distance"], dist.flatten(1).amin(-1))
    door_q = (p[..., None, :2] - door).norm(dim=-1).flatten(1).amin(-1) - DOOR_RADIUS - QUAD_RADIUS
    door_l = (p_load[:, None, :2] - door).norm(dim=-1).amin(-1) - DOOR_RADIUS - LOAD_RADIUS
    worst["min_door_clearance_quad"] = torch.minimum(worst["min_door_clearance_quad"], door_q)
    worst["min_door_clearance_load"] = torch.minimum(worst["min_door_clearance_load"], door_l)
    worst["max_z"] = torch.maximum(worst["max_z"], p[..., 2].amax(-1))
    worst["min_z"] = torch.minimum(worst["min_z"], torch.minimum(p[..., 2].amin(-1), p_load[:, 2]))
    cable = ((p - p_load[:, None]).norm(dim=-1) - cable_length).abs().amax(-1)
    worst["max_cable_error"] = torch.maximum(worst["max_cable_error"], cable)
    worst["min_qw"] = torch.minimum(worst["min_qw"], x[..., 3].amin(-1))


def failed_checks(
    worst: dict[str, torch.Tensor],  # name -> [B] worst values of a flight
    min_tension: float,
) -> dict[str, torch.Tensor]:
    """name → [B] whether each bound failed (the reasons a trajectory is rejected)."""
    return {
        "slack_cable": ~(worst["min_tension"] > min_tension),
        "load_not_below": ~(worst["min_height_gap"] > 0.3),
        "quad_collision": ~(worst["min_quad_distance"] > 2 * QUAD_RADIUS),
        "door_collision": ~((worst["min_door_clearance_quad"] > 0) & (worst["min_door_clearance_load"] > 0)),
        "out_of_room": ~((worst["max_z"] <= CEILING) & (worst["min_z"] >= 0)),
        "saturation": worst["saturated_ticks"] > 0,
        "cable_length": ~(worst["max_cable_error"] < 1e-4),
        "quaternion_flip": ~(worst["min_qw"] > 0),
        "goal_missed": worst["goal_error"] >= 0.1,  # NaN (run too short to judge) counts as held
    }


def bounds_held(
    worst: dict[str, torch.Tensor],  # name -> [B] worst values of a flight
    min_tension: float,
) -> torch.Tensor:
    """[B] the spec's §7 bounds: taut cables, load below quads, no collisions, inside the room, no saturation."""
    failures = failed_checks(worst, min_tension)
    return ~torch.stack(list(failures.values())).any(0)
