"""Flying doorway scenarios in closed loop: the 100 Hz control loop over the RK4 plant, and its record.

`fly` runs the controller at every tick (its thrusts held for `substeps` RK4 steps of the plant), folds the
spec's bounds into running worst values at every tick (the tensions at every RK4 step), and records x, load
and tensions at the sample times and u per `u_sampling`; `QuadrotorSwarm.rollout` turns that into a
`SwarmRollout` and judges it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from mpsim.data.trajectories import Trajectories
from mpsim.systems.quadrotor_control import GeometricController
from mpsim.systems.quadrotor_dynamics import QuadrotorPlant
from mpsim.systems.quadrotor_scenarios import DoorwayScenario, update_checks


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


def initial_checks(b: int, dtype: torch.dtype) -> dict[str, torch.Tensor]:
    """name → [B] the running worst values before the first tick (see `SwarmRollout.checks`)."""
    inf = torch.full((b,), math.inf, dtype=dtype)
    return {
        "min_tension": inf.clone(),
        "min_height_gap": inf.clone(),
        "min_quad_distance": inf.clone(),
        "min_door_clearance_quad": inf.clone(),
        "min_door_clearance_load": inf.clone(),
        "max_z": -inf,
        "min_z": inf.clone(),
        "saturated_ticks": torch.zeros(b, dtype=dtype),
        "max_cable_error": torch.zeros(b, dtype=dtype),
        "min_qw": inf.clone(),
    }


def fly(
    plant: QuadrotorPlant,
    controller: GeometricController,
    scenario: DoorwayScenario,
    horizon: int,
    ticks: int,
    substeps: int,
    control_dt: float,
    u_sampling: str,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
    """Fly `scenario` from its initial state for `horizon` samples of `ticks` control periods each.

    Returns:
        x [B, T, N, 13], load [B, T, 6], tensions [B, T, N] at the sample times, u [B, T, N, 4] (the mean
        applied thrust over the following sample interval for ``mean``, the thrust at the sample time for
        ``first``), and name → [B] the worst value of each bound over the flight (NaN where it diverged).
    """
    h = control_dt / substeps
    x, load = scenario.x0.clone(), scenario.load0.clone()
    b, n = x.shape[:2]
    xs = x.new_empty(b, horizon + 1, n, 13)
    loads, tensions = x.new_empty(b, horizon + 1, 6), x.new_empty(b, horizon + 1, n)
    us = x.new_empty(b, horizon + 1, n, 4)
    worst = initial_checks(b, x.dtype)
    # the extra sample interval after the last sample only supplies that sample's u
    for k in range(horizon + 1):
        xs[:, k], loads[:, k] = x, load
        u_sum = torch.zeros_like(us[:, 0])
        for j in range(ticks):
            t = (k * ticks + j) * control_dt
            u, saturated = controller.control(x, load, scenario, t)
            worst["saturated_ticks"] += saturated.to(x.dtype)
            update_checks(worst, x, load, plant.cable_length)
            u_sum = u_sum + u if u_sampling == "mean" or j == 0 else u_sum
            for i in range(substeps):
                x, load, tension, _ = plant.step(x, load, u, h)
                worst["min_tension"] = torch.minimum(worst["min_tension"], tension.amin(-1))
                if j == 0 and i == 0:
                    tensions[:, k] = tension
        us[:, k] = u_sum / ticks if u_sampling == "mean" else u_sum
    update_checks(worst, x, load, plant.cable_length)
    worst["min_tension"] = torch.minimum(worst["min_tension"], plant.derivatives(x, load, u).tension.amin(-1))
    return xs, loads, tensions, us, worst
