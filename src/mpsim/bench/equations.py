"""`model=equations` against the hand-written `model=physics`: one training step (rollout, loss, backward) of the
same equations, on pendulum2 and Lorenz10, side by side in one run.

Both models integrate with the same solver, so they do the same number of vector-field evaluations; the ratio
is the cost of the compiled spec (sympy → torch operations, neighbour sums over the data's graph, `lin(H)`)
against the hand-written code (the target is ≤ 1.5×). Repeats alternate between the two models so that a
change in machine load falls on both.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from mpsim.bench.common import Suite, timeit
from mpsim.data.trajectories import Inputs
from mpsim.metrics import LOSSES
from mpsim.models.base import Model
from mpsim.models.equations import EquationsModel
from mpsim.models.physics import PhysicsModel
from mpsim.solvers.odeint import ODESolver
from mpsim.systems.base import System
from mpsim.systems.lorenz import CoupledLorenz
from mpsim.systems.pendulum import CoupledPendulums

PENDULUM_SPEC: dict[str, Any] = {
    "states": ["theta", "omega"],
    "equations": {
        "theta": "omega",
        "omega": "-(gravity/length)*sin(theta) - (spring/mass)*cos(theta)*sum_nbr(sin(theta) - sin(theta_j))",
    },
    "learnable": ["gravity", "spring"],
}
LORENZ_SPEC: dict[str, Any] = {
    "states": ["x", "y", "z"],
    "equations": {
        "x": "sigma*(y - x) + coupling*lin(H)",
        "y": "x*(rho - z) - y + coupling*lin(H)",
        "z": "x*y - beta*z + coupling*lin(H)",
    },
    "learnable": ["sigma", "rho", "beta", "coupling"],
}


def twins(case: str, solver: ODESolver) -> tuple[System, Model, Model]:
    """(system, hand-written physics model, spec model) with the same equations and learnable parameters."""
    system: System
    spec: dict[str, Any]
    if case == "pendulum2":
        system = CoupledPendulums()
        p = system.params()
        spec = {**PENDULUM_SPEC, "params": {k: p[k] for k in ("gravity", "length", "spring", "mass")}}
    elif case == "lorenz10":
        lorenz = system = CoupledLorenz(name="lorenz10", n_nodes=10, coupling=1.0)
        spec = {
            **LORENZ_SPEC,
            "params": {
                "sigma": lorenz.sigma,
                "rho": lorenz.rho,
                "beta": lorenz.beta,
                "coupling": lorenz.coupling,
                "H": lorenz.H_unit.tolist(),
            },
        }
    else:
        raise ValueError(f"unknown case {case!r}; choose pendulum2 or lorenz10.")
    physics = PhysicsModel(
        system.state_dim, system=type(system)(**_args(system)), learnable=spec["learnable"], solver=solver
    )
    equations = EquationsModel(system.state_dim, spec=spec, solver=solver)
    return system, physics, equations


def _args(system: System) -> dict[str, Any]:
    if isinstance(system, CoupledLorenz):
        return {"name": system.name, "n_nodes": system.n_nodes, "coupling": system.coupling}
    return {}


class EquationsBench(Suite):
    """Args:
    cases: pendulum2 and/or lorenz10.
    batch: trajectories per training step.
    steps: output steps of each trajectory.
    solver: torchdiffeq method of both models (dopri5: adaptive, the default model solver; rk4: fixed).
    repeats: timing repeats per model (alternating).
    """

    name = "equations"

    def __init__(
        self,
        cases: Sequence[str] = ("pendulum2", "lorenz10"),
        batch: int = 32,
        steps: int = 50,
        solver: str = "dopri5",
        repeats: int = 7,
    ) -> None:
        self.cases, self.batch, self.steps, self.solver, self.repeats = list(cases), batch, steps, solver, repeats

    def run(self) -> list[dict[str, Any]]:
        rows = []
        loss_fn = LOSSES["huber"]
        for case in self.cases:
            solver = ODESolver(self.solver, rtol=1e-4, atol=1e-4)
            system, physics, equations = twins(case, solver)
            data = system.generate(self.batch, seed=0, horizon=self.steps)
            x = data.x.float()
            t = data.t.float()
            times: dict[str, list[float]] = {"physics": [], "equations": []}
            models = {"physics": physics, "equations": equations}
            for model in models.values():
                model.set_normalisation(x.reshape(-1, x.shape[-1]).mean(0), x.reshape(-1, x.shape[-1]).std(0))
            inputs = Inputs(data.edge_index)
            with torch.no_grad():  # the same equations: the same prediction
                gap = float((physics.rollout(x[:, 0], t, inputs) - equations.rollout(x[:, 0], t, inputs)).abs().max())

            def step(model: Model, x=x, t=t, inputs=inputs) -> None:  # x: [B, T, N, D]
                model.zero_grad()
                pred = model.rollout(x[:, 0], t, inputs)
                loss_fn(model.normalise(pred), model.normalise(x), 1.0).backward()

            for _ in range(self.repeats):  # alternate, so that load changes fall on both
                for name, model in models.items():
                    times[name].append(timeit(functools.partial(step, model), repeats=1, warmup=1)["min_s"])
            phys, eq = sorted(times["physics"]), sorted(times["equations"])
            med_p, med_e = phys[len(phys) // 2], eq[len(eq) // 2]
            rows.append(
                {
                    "case": case,
                    "N": system.n_nodes,
                    "B": self.batch,
                    "steps": self.steps,
                    "solver": self.solver,
                    "physics_step_s": med_p,
                    "equations_step_s": med_e,
                    "ratio": med_e / med_p,
                    "ratio_min": eq[0] / phys[0],
                    "max_prediction_gap": gap,
                }
            )
        return rows

    def summarise(self, rows: list[dict[str, Any]]) -> list[str]:
        return [
            f"- {r['case']} (N={r['N']}, B={r['B']}, {r['steps']} steps, {r['solver']}): spec model / hand-written "
            f"physics model = {r['ratio']:.2f}× per training step (median; {r['ratio_min']:.2f}× of the minima); "
            f"predictions agree to {r['max_prediction_gap']:.1e}"
            for r in rows
        ]

    def plot(self, rows: list[dict[str, Any]], out_dir: Path) -> list[str]:
        from mpsim.plotting import save_figure, subplots

        fig, ax = subplots(figsize=(5, 3.2))
        labels = [r["case"] for r in rows]
        pos = torch.arange(len(rows)).tolist()
        ax.bar([p - 0.2 for p in pos], [1e3 * r["physics_step_s"] for r in rows], 0.4, label="physics (hand-written)")
        ax.bar([p + 0.2 for p in pos], [1e3 * r["equations_step_s"] for r in rows], 0.4, label="equations (spec)")
        ax.set_xticks(pos, labels)
        ax.set(ylabel="training step (ms)", title="spec model vs hand-written model")
        ax.legend()
        return [str(save_figure(fig, Path(out_dir) / "equations_vs_physics.png"))]
