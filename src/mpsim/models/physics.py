"""`physics`: a white-box model — a system's declared equations with chosen physical parameters learnable.

The model wraps a `System` (built from the same config as the data's system) and replaces the named float
parameters (e.g. `gravity` and `spring` of the pendulums; `sigma`, `rho`, `beta` of Lorenz) by trainable
tensors, so the same trainer fits them by full-rollout shooting. The system's own effects are dropped:
they describe the data, not what the scientist's model knows. What the model lacks is found by
`mpsim diagnose` and added back as `model.effects`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import nn

from mpsim.data.trajectories import Inputs
from mpsim.effects import Effect, EffectContext, total
from mpsim.errors import ConfigError
from mpsim.graphs.batch import batch_graph
from mpsim.models.base import Model
from mpsim.solvers.odeint import ODESolver
from mpsim.systems.base import System


class _PhysicsField(nn.Module):
    def __init__(self, model: PhysicsModel, ctx_graph) -> None:
        super().__init__()
        self.model, self.ctx_graph = model, ctx_graph

    def forward(self, t: torch.Tensor, x: torch.Tensor, history=None) -> torch.Tensor:  # x: [B, N, D] raw
        model = self.model
        dx = model.system.dynamics(t, x)
        if len(model.effects):
            dx = dx + total(model.effects, t, x, EffectContext(self.ctx_graph, history))
        return dx


class PhysicsModel(Model):
    """A system's equations with learnable physical parameters (plus optional learnable effects).

    Args:
        state_dim, control_dim: set from the data (must match the system's).
        system: the `System` whose `dynamics` define the model (its effects are ignored).
        learnable: names of the system's float attributes to train (default: every float in `params()`).
        init: optional starting values {name: value} (default: the system's declared values).
        effects: extra named terms with learnable coefficients.
        solver: ODE solver of the rollouts.
    """

    def __init__(
        self,
        state_dim: int,
        system: System,
        control_dim: int = 0,
        learnable: Sequence[str] | None = None,
        init: dict[str, float] | None = None,
        effects: Sequence[Effect] = (),
        solver: ODESolver | None = None,
    ) -> None:
        super().__init__(state_dim, control_dim, effects)
        if system.state_dim != state_dim:
            raise ConfigError(
                f"model=physics uses {system.name}'s equations ({system.state_dim} states per node) but the data has "
                f"{state_dim}. Point model.system at the system that matches the data."
            )
        system.effects = []  # the data's hidden terms are not part of the declared model
        self.system = system
        self.solver = solver or ODESolver()
        floats = {k: v for k, v in system.params().items() if isinstance(v, float)}
        names = list(floats) if learnable is None else list(learnable)
        unknown = [n for n in names if not isinstance(getattr(system, n, None), float)]
        if unknown:
            raise ConfigError(
                f"model.learnable names {unknown}, which are not float parameters of {type(system).__name__}; "
                f"choose from {sorted(floats)}."
            )
        init = dict(init or {})
        # positive physical constants are trained in log space so they stay positive
        self.positive = [n for n in names if float(getattr(system, n)) > 0]
        self.raw = nn.ParameterDict()
        for n in names:
            value = float(init.get(n, getattr(system, n)))
            self.raw[n] = nn.Parameter(torch.tensor(math.log(value) if n in self.positive else value))
        self.declared = {n: float(getattr(system, n)) for n in names}

    @property
    def kinematic_states(self) -> list[str]:
        """States whose declared equation is another state (θ̇ = ω), found by evaluating the equations at random
        states: they carry no physics, and the residual loop does not search them by default."""
        if not hasattr(self, "_kinematic"):
            names = list(self.system.state_names)
            x = torch.randn(
                4, self.system.n_nodes, len(names), dtype=torch.float64, generator=torch.Generator().manual_seed(0)
            )
            try:
                with torch.no_grad():
                    f = self.system.dynamics(torch.tensor(0.0, dtype=torch.float64), x)
                self._kinematic = [
                    names[d]
                    for d in range(len(names))
                    if any(j != d and torch.equal(f[..., d], x[..., j]) for j in range(len(names)))
                ]
            except Exception:  # noqa: BLE001 - equations that need controls or more context: declare none
                self._kinematic = []
        return self._kinematic

    def parameters_now(self) -> dict[str, torch.Tensor]:
        """{name: current value tensor} of the learnable physical parameters."""
        return {n: (p.exp() if n in self.positive else p) for n, p in self.raw.items()}

    def rollout(
        self,
        x0: torch.Tensor,  # [B, N, D] initial states (raw units)
        t: torch.Tensor,  # [T] times
        inputs: Inputs,  # only the graph, read by effects; the system's own graph is used for its equations
    ) -> torch.Tensor:
        if x0.shape[1] != self.system.n_nodes:
            raise ConfigError(
                f"model=physics was built for {self.system.name} with {self.system.n_nodes} nodes but the data has "
                f"{x0.shape[1]}; point model.system at a system of that size."
            )
        for name, value in self.parameters_now().items():
            setattr(self.system, name, value.to(x0))  # the equations read plain attributes
        b, n, _ = x0.shape
        graph = batch_graph(inputs.edge_index.to(x0.device), b, n, dtype=x0.dtype) if len(self.effects) else None
        try:
            return self.integrate(_PhysicsField(self, graph), x0, t, self.solver, inputs.past)
        finally:
            for name in self.raw:
                setattr(self.system, name, self.declared[name])

    def sensitivities(self, t, x, edge_index):
        """[M, N, D, P] ∂f/∂p of the declared equations at the given states, one forward-mode derivative per
        learnable parameter (P is a handful)."""
        values = {n: v.detach().to(x) for n, v in self.parameters_now().items()}
        columns = []
        try:
            for name in values:  # a loop over the few physical parameters

                def field(v, name=name):
                    for other, val in values.items():
                        setattr(self.system, other, v if other == name else val)
                    return self.system.dynamics(t, x)

                _, tangent = torch.func.jvp(field, (values[name],), (torch.ones_like(values[name]),))
                columns.append(tangent)
        finally:
            for name in self.raw:
                setattr(self.system, name, self.declared[name])
        return torch.stack(columns, dim=-1)

    def sensitivity_names(self) -> list[str]:
        return list(self.raw)

    def shift_parameters(self, shifts: dict[str, float]) -> None:
        with torch.no_grad():
            for name, delta in shifts.items():
                value = float(self.parameters_now()[name]) + delta
                if name in self.positive and value <= 0:
                    continue  # a shift that would flip the sign of a positive constant is not applied
                self.raw[name].fill_(math.log(value) if name in self.positive else value)

    def report(self) -> dict[str, Any]:
        values = {n: float(v.detach()) for n, v in self.parameters_now().items()}
        return {"physical_parameters": values, "effects": [e.describe() for e in self.effects]}

    def report_lines(self) -> list[tuple[str, str]]:
        values = ", ".join(f"{n}={float(v.detach()):.5g}" for n, v in self.parameters_now().items())
        rows = [("fitted parameters", values)]
        rows += [("effect", e.describe()) for e in self.effects]
        return rows
