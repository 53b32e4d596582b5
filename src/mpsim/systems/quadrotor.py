"""A swarm of N quadrotors carrying a cable-suspended point-mass load through a doorway (MP-NODE's quad3/quad6).

MP-NODE's own generator is not public; this follows our spec (`shared/reference/quadrotor_spec.md`), whose
physical and door parameters come from Jackson et al., RA-L 2020. Node = one quadrotor (13 states, 4 rotor
thrusts as controls); the load is not a node (it is not homogeneous with the quads) and is returned beside the
node data. The parts, one module each:

- `quadrotor_dynamics`: the equations of motion (`QuadrotorPlant`: rigid unilateral cables whose tensions are
  solved at every right-hand-side evaluation, fixed-step RK4, mechanical energy).
- `quadrotor_control`: the closed loop (`GeometricController`: SE(3) tracking at 100 Hz with a tension
  feed-forward).
- `quadrotor_scenarios`: the doorway manoeuvre (`DoorwayScenarios`, the min-jerk reference) and the spec's bounds.
- `quadrotor_flight`: one closed-loop flight (`fly`: the 100 Hz loop over the RK4 plant) and its record
  (`SwarmRollout`).

This module composes them into the `System` that data are generated from: `QuadrotorSwarm` flies random
scenarios in closed loop (the plant integrated with RK4 within each control hold) and rejects and resamples the
trajectories that break a bound (a slack cable, which this model cannot represent, a collision, saturation, ...).
Its parts are public: `swarm.plant` (derivatives, RK4 `step`, mechanical energy), `swarm.controller` (`control`,
`hover_state`) and `quadrotor_scenarios.reference(scenario, t, swarm.cable_length)`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import torch

from mpsim.data.trajectories import Trajectories
from mpsim.errors import ConfigError, IncompatibleError
from mpsim.graphs.topology import complete
from mpsim.systems.base import System, check_fixed_steps
from mpsim.systems.quadrotor_control import GeometricController
from mpsim.systems.quadrotor_dynamics import QuadrotorPlant
from mpsim.systems.quadrotor_flight import SwarmRollout, fly
from mpsim.systems.quadrotor_scenarios import (
    CEILING,
    DOOR_CENTRES,
    DOOR_RADIUS,
    LOAD_RADIUS,
    QUAD_RADIUS,
    SETTLE_TIME,
    DoorwayScenario,
    DoorwayScenarios,
    bounds_held,
    failed_checks,
)


def _check_arguments(
    n_quads: int,
    effects: Sequence[Any],
    u_sampling: str,
    control_dt: float,
    substeps: int,
    quad_mass: float,
    load_mass: float,
    arm: float,
    cable_length: float,
    inertia: Sequence[float],
) -> None:
    """Raise a `ConfigError` for a `QuadrotorSwarm` argument out of range."""
    if n_quads < 1:
        raise ConfigError(f"system.n_quads must be >= 1; got {n_quads}.")
    if effects:
        raise ConfigError("system=quadrotor does not take effects (its data are closed-loop); set effects=[].")
    if u_sampling not in ("mean", "first"):
        raise ConfigError(f"system.u_sampling must be 'mean' or 'first'; got {u_sampling!r}.")
    if control_dt <= 0 or substeps < 1:
        raise ConfigError(f"need control_dt > 0 and substeps >= 1; got {control_dt}, {substeps}.")
    physical = {"quad_mass": quad_mass, "load_mass": load_mass, "arm": arm, "cable_length": cable_length}
    physical.update({f"inertia[{k}]": v for k, v in enumerate(inertia)})
    bad = {k: v for k, v in physical.items() if not (math.isfinite(float(v)) and float(v) > 0)}
    if bad:
        raise ConfigError(
            f"system.{', system.'.join(bad)} must be > 0 (masses, lengths, moments of inertia); got "
            f"{', '.join(str(v) for v in bad.values())}."
        )


def _default_fan_half_angle(n_quads: int, cable_length: float) -> tuple[float, float]:
    """[40, 50] degrees for N ≤ 3; otherwise [b, b + 5] with b = (N − 1)·asin(0.35/L)."""
    if n_quads <= 3:
        return (40.0, 50.0)
    # neighbouring fan slots are 2L·sin(β/(N−1)) apart: keep that ≥ 0.7 m (> 2 quad radii)
    low = (n_quads - 1) * math.degrees(math.asin(0.35 / cable_length))
    return (low, low + 5.0)


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
        _check_arguments(
            n_quads, effects, u_sampling, control_dt, substeps, quad_mass, load_mass, arm, cable_length, inertia
        )
        super().__init__(name, n_quads, complete(n_quads), effects)
        self.dt, self.horizon = float(dt), int(horizon)
        self.control_dt, self.substeps = float(control_dt), int(substeps)
        self._set_physics(quad_mass, load_mass, inertia, arm, torque_coeff, cable_length, gravity, rotor_max, baumgarte)
        self.min_tension = float(min_tension)
        self.kp, self.kd = float(kp), float(kd)
        self.k_rot, self.k_omega = tuple(float(v) for v in k_rot), tuple(float(v) for v in k_omega)
        self.ff_damping = float(ff_damping)
        self._set_scenario_ranges(fan_half_angle, r_config_range, z_door_range, phase_ranges)
        self.attitude_noise, self.velocity_noise = float(attitude_noise), float(velocity_noise)
        self.dither = float(dither)
        self.u_sampling, self.max_rounds = u_sampling, int(max_rounds)
        self.threads = None if threads is None else int(threads)
        if not 0 < self.r_config_range[0] <= self.r_config_range[1] < self.cable_length:
            raise ConfigError(
                f"system.r_config_range must lie in (0, cable_length={self.cable_length}); got {self.r_config_range}."
            )
        self._build_parts()

    def _set_physics(
        self,
        quad_mass: float,
        load_mass: float,
        inertia: Sequence[float],
        arm: float,
        torque_coeff: float,
        cable_length: float,
        gravity: float,
        rotor_max: float | None,
        baumgarte: Sequence[float],
    ) -> None:
        """Store the physical parameters as floats; rotor_max None gives (m_q + m_L) g / 4."""
        self.quad_mass, self.load_mass = float(quad_mass), float(load_mass)
        self.inertia = tuple(float(v) for v in inertia)
        self.arm, self.torque_coeff = float(arm), float(torque_coeff)
        self.cable_length, self.gravity = float(cable_length), float(gravity)
        self.rotor_max = (self.quad_mass + self.load_mass) * self.gravity / 4 if rotor_max is None else float(rotor_max)
        self.baumgarte = tuple(float(v) for v in baumgarte)

    def _set_scenario_ranges(
        self,
        fan_half_angle: Sequence[float] | None,
        r_config_range: Sequence[float],
        z_door_range: Sequence[float],
        phase_ranges: Sequence[Sequence[float]],
    ) -> None:
        """Store the scenario ranges as float tuples; fan_half_angle None gives the range for N quads."""
        if fan_half_angle is None:
            fan_half_angle = _default_fan_half_angle(self.n_nodes, self.cable_length)
        self.fan_half_angle = tuple(float(v) for v in fan_half_angle)
        self.r_config_range = tuple(float(v) for v in r_config_range)
        self.z_door_range = tuple(float(v) for v in z_door_range)
        self.phase_ranges = tuple(tuple(float(v) for v in r) for r in phase_ranges)

    def _build_parts(self) -> None:
        """The plant, the controller and the scenario distribution, from the stored parameters."""
        self.plant = QuadrotorPlant(
            self.n_nodes,
            self.quad_mass,
            self.load_mass,
            self.inertia,
            self.arm,
            self.torque_coeff,
            self.cable_length,
            self.gravity,
            self.baumgarte,
        )
        self.controller = GeometricController(
            self.plant, self.kp, self.kd, self.k_rot, self.k_omega, self.ff_damping, self.rotor_max, self.dither
        )
        self.scenarios = DoorwayScenarios(
            self.n_nodes,
            self.cable_length,
            self.fan_half_angle,
            self.r_config_range,
            self.z_door_range,
            self.phase_ranges,
            self.attitude_noise,
            self.velocity_noise,
            self.dither,
        )

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

    # ---- plant (`self.plant`: `QuadrotorPlant`; `self.controller`: `GeometricController`) -------------------
    def dynamics(
        self,
        t: torch.Tensor,  # [] time
        x: torch.Tensor,  # [B, N, 13] quad states
        u: torch.Tensor | None = None,  # [B, N, 4] rotor thrusts
    ) -> torch.Tensor:
        raise IncompatibleError(
            "QuadrotorSwarm couples its quads through the load, whose state is not part of x [B, N, 13]; "
            "call `plant.derivatives(x, load, u)` (or `plant.step`) with the load state, e.g. from `generate_full`."
        )

    # ---- scenarios --------------------------------------------------------------------------------------
    def sample_scenarios(self, n: int, generator: torch.Generator) -> DoorwayScenario:
        """`n` random doorway scenarios (spec §5) with their trim initial states, drawn with `generator`."""
        return self.scenarios.sample(n, generator, self.controller.trim_attitude)

    def sample_initial_states(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """[n, N, 13] initial quad states of `n` random scenarios (use `sample_scenarios` to fly them)."""
        return self.sample_scenarios(n, generator).x0

    # ---- data ----------------------------------------------------------------------------------------
    def _ticks_per_sample(self, dt: float) -> int:
        k = round(dt / self.control_dt)
        if k < 1 or not math.isclose(k * self.control_dt, dt, rel_tol=1e-9, abs_tol=1e-12):
            raise ConfigError(
                f"quadrotor data need dt to be a whole multiple of control_dt={self.control_dt}; got dt={dt}. "
                f"Set system.dt to e.g. {max(1, k) * self.control_dt:g}."
            )
        check_fixed_steps(self.name, k * self.substeps, dt, self.dt)
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
        xs, loads, tensions, us, worst = fly(
            self.plant, self.controller, scenario, horizon, ticks, self.substeps, self.control_dt, self.u_sampling
        )
        # a diverged (NaN) trajectory gets the failing extreme of every check
        worst = {key: torch.nan_to_num(val, nan=-math.inf if key.startswith("min") else math.inf)
                 for key, val in worst.items()}  # fmt: skip
        settled = horizon * dt >= scenario.durations.sum(-1) + SETTLE_TIME
        goal_error = (loads[:, -1, :3] - scenario.goal).norm(dim=-1)
        worst["goal_error"] = torch.where(settled, goal_error, torch.full_like(goal_error, math.nan))
        accepted = (
            bounds_held(worst, self.min_tension)
            & torch.isfinite(xs).flatten(1).all(-1)
            & torch.isfinite(us).flatten(1).all(-1)
        )
        traj = Trajectories(  # NaN zeroed so that the container validates; `accepted` is False there
            t=torch.arange(horizon + 1, dtype=torch.float64) * dt,
            x=torch.nan_to_num(xs),
            u=torch.nan_to_num(us),
            edge_index=self.edge_index,
            meta=self.meta(dt),
        )
        return SwarmRollout(traj, loads, tensions, scenario, worst, accepted)

    def failed_checks(self, worst: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:  # worst: name -> [B]
        """name → [B] whether each bound failed (the reasons a trajectory is rejected)."""
        return failed_checks(worst, self.min_tension)

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
        burn_in: int = 0,
    ) -> Trajectories:
        """`n` accepted trajectories (node data only; see `generate_full`). rtol/atol are unused (fixed-step RK4);
        `burn_in` must be 0 (each scenario starts at rest on its own trajectory)."""
        if burn_in:
            raise ConfigError(f"{self.name}: quadrotor data has no burn-in; got burn_in={burn_in}. Set data.burn_in=0.")
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
