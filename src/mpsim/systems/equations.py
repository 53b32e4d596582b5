"""`system=equations`: ground truth simulated from a spec written in the config (`mpsim.equations`).

    mpsim simulate system=equations system.spec=my_pendulums.yaml format=csv

The same spec that `model=equations` trains (states, equations, params) plus what a simulation needs: the
graph (a topology name or an edge list), initial-state ranges and, optionally, the sampling step and length.
`system.effects=[...]` adds hidden terms as for any system, so a user can make a synthetic twin of an
experiment and check that `mpsim diagnose` finds what was put in.

Extra spec keys (each may also be given under `system.`, which wins):

    name: my_pendulums        # dataset/checkpoint name (default: the spec file's name)
    nodes: 2                  # N (or implied by per-node parameters or the edge list)
    graph: complete           # complete | chain | ring | grid | erdos_renyi | barabasi_albert | watts_strogatz
                              # (ring: shift(x, k) wraps around unless the spec sets shift_boundary)
    graph_params: {p: 0.5}    # the family's parameters (seed, p, k, m, rows)
    edges: [[0, 1]]           # or an explicit edge list [sender, receiver]
    directed: false           # false: every listed edge also runs the other way
    init: {theta: [-1.5, 1.5], omega: [-1, 1]}   # uniform initial ranges per state (default [-1, 1])
    dt: 0.1                   # default sampling step
    horizon: 50               # default steps per trajectory
    integrator: dopri5        # dopri5 (adaptive, default) | semi_implicit_euler (fixed step, as physics engines)
    substep: 0.005            # semi_implicit_euler's step h; dt must be a whole number of steps
    input: {kind: multisine, band: [0.1, 2.0], hold: zoh, seed: 0}   # the signal driving the spec's inputs

A driven spec (`inputs: [u, ...]`) needs `input`: a generator (multisine, steps, chirp, prbs) or a CSV column
(`{file: u.csv, column: u}`), every key in `mpsim.systems.inputs`. The generated u [B, T, N, C] is stored in the
data (`control_names` = the spec's inputs, `meta["input_hold"]` = the signal's hold), and the ground truth
integrates exactly that input: zoh piecewise constant (dopri5 steps to every sample time and restarts there, so
no step straddles a jump), linear interpolated (dopri5 steps to every sample time, where the slope changes).

`integrator: semi_implicit_euler` steps as rigid-body engines do (symplectic Euler): every dynamic row first,
v_{k+1} = v_k + h·f_v(t_k, x_k, v_k), then the kinematic rows (`kinematic`, by default those whose equation is
another state) with the updated state, x_{k+1} = x_k + h·f_x(t_k, x_k, v_{k+1}); the state is logged every dt.
Such data carry the scheme's O(h) error, which a model integrated otherwise does not share: the artefact
`mpsim diagnose` must not read as physics.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torchdiffeq import odeint

from mpsim.data.trajectories import Trajectories, grid_step
from mpsim.effects import min_delay
from mpsim.errors import ConfigError, did_you_mean
from mpsim.graphs.batch import BatchedGraph, batch_graph
from mpsim.graphs.topology import make_topology
from mpsim.signals import HOLD_KEY, GridInput
from mpsim.solvers.dde import delay_substeps, rk4_delay
from mpsim.solvers.odeint import ADAPTIVE
from mpsim.spec import SYSTEM_KEYS, EquationField, check_nodes, merge_spec, parse_spec
from mpsim.systems.base import GROUND_TRUTH_MAX_STEPS, System, check_fixed_steps
from mpsim.systems.inputs import InputSignals

SAFE_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")
INTEGRATORS = ("dopri5", "semi_implicit_euler")


class EquationsSystem(System):
    """Ground truth from a spec; node states as the spec's `states`.

    Args:
        spec: the spec as a mapping (`system.spec=<file>` is loaded by the command layer).
        name, n_nodes, graph, graph_params, edges, directed, init, dt, horizon, integrator, substep, input,
            shift_boundary: as the spec's keys of the same meaning (`n_nodes` is the spec's `nodes`); given here they
            win over the spec's.
        effects: extra terms added to the dynamics.

    Raises:
        ConfigError: a key the simulation cannot use (one message: what, where, the fix).
    """

    def __init__(
        self,
        spec: dict[str, Any] | None = None,
        name: str | None = None,
        n_nodes: int | None = None,
        graph: str | None = None,
        graph_params: dict[str, Any] | None = None,
        edges: list[list[int]] | None = None,
        directed: bool | None = None,
        init: dict[str, list[float]] | None = None,
        dt: float | None = None,
        horizon: int | None = None,
        effects: Sequence[Any] = (),
        integrator: str | None = None,
        substep: float | None = None,
        input: dict[str, Any] | None = None,
        shift_boundary: str | float | None = None,
    ) -> None:
        over = {
            "name": name,
            "nodes": n_nodes,
            "graph": graph,
            "graph_params": graph_params,
            "edges": edges,
            "directed": directed,
            "init": init,
            "dt": dt,
            "horizon": horizon,
            "integrator": integrator,
            "substep": substep,
            "input": input,
            "shift_boundary": shift_boundary,
        }
        raw = merge_spec(spec, over, "system")
        self.spec = parse_spec(raw, "system.spec", extra_keys=SYSTEM_KEYS)
        self.state_names = self.spec.states  # per instance: the spec names them
        self.control_names = self.spec.inputs
        self.input = self._input(raw.get("input"))
        self.field = EquationField(self.spec)
        name = str(raw.get("name") or "equations")
        if not SAFE_NAME.match(name):
            raise ConfigError(f"system.name={name!r}: use letters, digits, '_', '.', '-' only (it names files).")
        edge_index, n = self._graph(raw)
        check_nodes(self.spec, n, "system.spec")
        super().__init__(name, n, edge_index, effects)
        self.ranges = self._ranges(raw.get("init"))
        if raw.get("dt") is not None:
            if not isinstance(raw["dt"], int | float) or raw["dt"] <= 0:
                raise ConfigError(f"system.dt must be a positive number; got {raw['dt']!r}.")
            self.dt = float(raw["dt"])
        if raw.get("horizon") is not None:
            if not isinstance(raw["horizon"], int) or raw["horizon"] < 1:
                raise ConfigError(f"system.horizon must be a positive integer; got {raw['horizon']!r}.")
            self.horizon = int(raw["horizon"])
        self.integrator, self.substep = self._integrator(raw.get("integrator"), raw.get("substep"))
        if self.integrator == "semi_implicit_euler":
            if raw.get("dt") is not None:
                self._steps_per_interval(torch.tensor([0.0, self.dt], dtype=torch.float64), "system.dt")
            if min_delay(self.effects) > 0:
                raise ConfigError(
                    "system.integrator=semi_implicit_euler cannot integrate a DelayedFeedback effect "
                    "(it needs the state history); use system.integrator=dopri5."
                )
        self.values = dict(self.spec.params)
        self.raw = self.spec.raw
        self._graphs: dict[tuple, BatchedGraph] = {}
        self._seed: int | None = None  # the dataset seed while `generate` runs (the inputs' realisations)

    def _input(self, config: Any) -> InputSignals | None:
        """The signal driving the spec's inputs (None without inputs)."""
        if not self.spec.inputs:
            if config is not None:
                raise ConfigError(
                    "system.input is given but system.spec declares no inputs; declare them (inputs: [u]) and use "
                    "them in the equations, or remove system.input."
                )
            return None
        if config is None:
            raise ConfigError(
                f"system.spec declares the inputs {list(self.spec.inputs)} but no signal drives them; set "
                "system.input, e.g. {kind: multisine, band: [0.1, 2.0]} or {file: u.csv, column: u} "
                "(docs/equations.md)."
            )
        return InputSignals(config, self.spec.inputs)

    @staticmethod
    def _integrator(name: Any, substep: Any) -> tuple[str, float | None]:
        name = "dopri5" if name is None else name
        if name not in INTEGRATORS:
            raise ConfigError(
                f"system.integrator={name!r} is not an integrator.{did_you_mean(str(name), INTEGRATORS)}"
                f" Choose one of {', '.join(INTEGRATORS)}."
            )
        if name == "dopri5":
            if substep is not None:
                raise ConfigError(
                    f"system.substep={substep!r} is the step of integrator=semi_implicit_euler; dopri5 "
                    "chooses its own steps. Remove substep, or set integrator: semi_implicit_euler."
                )
            return name, None
        if substep is None:
            raise ConfigError(
                "system.integrator=semi_implicit_euler needs its step: set substep: <h> (e.g. 0.005; "
                "the sampling step dt must be a whole number of steps h)."
            )
        ok = isinstance(substep, int | float) and not isinstance(substep, bool) and math.isfinite(substep)
        if not ok or substep <= 0:
            raise ConfigError(f"system.substep must be a positive number (the Euler step h); got {substep!r}.")
        return name, float(substep)

    def _steps_per_interval(
        self,
        t: torch.Tensor,  # [T] output times
        where: str = "the sampling step (system.dt or data.dt)",
    ) -> list[int]:
        """Euler steps of size `substep` between consecutive output times (each interval a whole number of them)."""
        assert self.substep is not None  # set with integrator=semi_implicit_euler, the only caller
        intervals = (t[1:] - t[:-1]).double()
        steps = torch.round(intervals / self.substep)
        bad = (steps < 1) | ((intervals - steps * self.substep).abs() > 1e-9 * torch.clamp(intervals.abs(), min=1.0))
        if bool(bad.any()):
            step = float(intervals[bad][0])
            raise ConfigError(
                f"{where} = {step:g} is not a whole multiple of system.substep = {self.substep:g} "
                "(integrator=semi_implicit_euler logs the state every k Euler steps). Set dt to k·substep, "
                f"e.g. dt={max(1, round(step / self.substep)) * self.substep:g}, or change substep."
            )
        return [int(k) for k in steps.tolist()]

    def _graph(self, raw: Mapping[str, Any]) -> tuple[torch.Tensor, int]:
        edges, kind = raw.get("edges"), raw.get("graph")
        n = raw.get("nodes") if raw.get("nodes") is not None else self.spec.n_nodes
        if edges is not None and kind is not None:
            raise ConfigError("system: give either graph=<topology> or edges=[[src, dst], ...], not both.")
        if edges is not None:
            ok = isinstance(edges, Sequence) and all(
                isinstance(e, Sequence)
                and len(e) == 2
                and all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in e)
                for e in edges
            )
            if not ok:
                raise ConfigError(
                    f"system.edges must be a list of [sender, receiver] pairs of node ids >= 0; got {str(edges)[:80]}."
                )
            ei = torch.tensor(list(edges), dtype=torch.long).reshape(-1, 2).T
            largest = int(ei.max()) + 1 if ei.numel() else 1
            n = largest if n is None else n
            if largest > n:
                raise ConfigError(f"system.edges names node {largest - 1} but there are {n} nodes (ids 0..{n - 1}).")
            if not raw.get("directed"):
                ei = torch.unique(torch.cat([ei, ei.flip(0)], dim=1), dim=1)
            return ei, int(n)
        if n is None:
            raise ConfigError(
                "system: the number of nodes is unknown; set nodes: N in the spec (or system.n_nodes), "
                "or give per-node parameters or an edge list."
            )
        if not isinstance(n, int) or n < 1:
            raise ConfigError(f"system.nodes must be a positive integer; got {n!r}.")
        if n == 1 or (kind is None and not self.field.uses_graph):
            return torch.zeros(2, 0, dtype=torch.long), n
        if kind is None:
            raise ConfigError(
                "system: the equations have neighbour terms but no graph; set graph: <topology> "
                "(complete, chain, ring, ...) or edges: [[src, dst], ...]."
            )
        params = raw.get("graph_params") or {}
        if not isinstance(params, Mapping):
            raise ConfigError(f"system.graph_params must be a mapping; got {params!r}.")
        return make_topology(str(kind), n, **params), n

    def _ranges(self, init: Any) -> torch.Tensor:
        """[D, 2] uniform initial ranges, [-1, 1] where the spec gives none."""
        ranges = torch.tensor([[-1.0, 1.0]] * self.spec.state_dim, dtype=torch.float64)
        if init is None:
            return ranges
        if not isinstance(init, Mapping):
            raise ConfigError(f"system.init must map state names to [low, high]; got {init!r}.")
        for state, bounds in init.items():
            if state not in self.spec.states:
                raise ConfigError(f"system.init.{state}: not a state; states: {list(self.spec.states)}.")
            ok = (
                isinstance(bounds, Sequence)
                and len(bounds) == 2
                and all(isinstance(v, int | float) and not isinstance(v, bool) for v in bounds)
            )
            if not ok or bounds[0] > bounds[1]:
                raise ConfigError(f"system.init.{state} must be [low, high] with low <= high; got {bounds!r}.")
            ranges[self.spec.states.index(state)] = torch.tensor([float(v) for v in bounds], dtype=torch.float64)
        return ranges

    def params(self) -> dict[str, Any]:
        return {"n_nodes": self.n_nodes, "spec": self.raw}

    def dynamics(
        self,
        t: torch.Tensor,  # [] time
        x: torch.Tensor,  # [B, N, D] node states
        u: torch.Tensor | None = None,  # [B, N, C] the spec's inputs at t (None without inputs)
    ) -> torch.Tensor:
        graph = None
        if self.field.uses_graph:
            key = (x.shape[0], x.device, x.dtype)
            if key not in self._graphs:
                self._graphs[key] = batch_graph(self.edge_index.to(x.device), x.shape[0], x.shape[1], dtype=x.dtype)
            graph = self._graphs[key]
        values = {k: v.to(x) for k, v in self.values.items()}
        return self.field(t, x, values, graph, u)

    # ---- data ----------------------------------------------------------------------------------------
    def generate(self, n, seed, dt=None, horizon=None, rtol=1e-8, atol=1e-10, burn_in=0) -> Trajectories:
        """As `System.generate`; a driven spec's inputs are drawn from `seed` too (one realisation each)."""
        self._seed = int(seed)
        try:
            return super().generate(n, seed, dt=dt, horizon=horizon, rtol=rtol, atol=atol, burn_in=burn_in)
        finally:
            self._seed = None

    def simulate(
        self,
        x0: torch.Tensor,  # [B, N, D] initial states
        t: torch.Tensor,  # [T] output times
        rtol: float = 1e-8,
        atol: float = 1e-10,
        method: str = "dopri5",
        u: torch.Tensor | None = None,  # [B, T, N, C] inputs (default: drawn from system.input)
    ) -> Trajectories:
        """The ground truth from `x0`; a driven spec integrates the inputs `u` (drawn from `system.input` with the
        dataset's seed when not given), held as the signal's `hold` says, and stores them in the data."""
        if self.input is None:
            if u is not None:
                raise ConfigError("system.spec declares no inputs; simulate it without u.")
            return super().simulate(x0, t, rtol, atol, method)
        x0, t = x0.to(torch.float64), t.to(torch.float64)
        want = (x0.shape[0], t.numel(), x0.shape[1], self.spec.input_dim)
        if u is None:
            u = self.input.sample(t, x0.shape[0], x0.shape[1], 0 if self._seed is None else self._seed)
        elif tuple(u.shape) != want:
            raise ConfigError(f"simulate: u must be [B, T, N, C] = {list(want)}; got {list(u.shape)}.")
        signal = GridInput(t, u.to(x0), self.input.hold)
        with torch.no_grad():  # ground truth: effect coefficients are constants here
            x = self._driven(x0, t, signal, rtol, atol, method)
        meta = {**self.meta(grid_step(t)), HOLD_KEY: self.input.hold}
        return Trajectories(t=t, x=x.contiguous(), edge_index=self.edge_index, u=signal.u, meta=meta)

    def _driven(self, x0, t, signal: GridInput, rtol, atol, method) -> torch.Tensor:
        """[B, T, N, D] the driven ground truth (x0 [B, N, D], t [T]): the input read from `signal` at each time."""
        if self.integrator == "semi_implicit_euler":
            assert self.substep is not None  # _integrator requires it for semi_implicit_euler
            return semi_implicit_euler(
                lambda tt, xx: self.rhs(tt, xx, signal(tt)),
                self._kinematic_mask(x0),
                x0,
                t,
                self.substep,
                self._steps_per_interval(t),
            )
        delay = min_delay(self.effects)
        if delay > 0:  # the input read at each RK4 stage's time (a stage on a sample time sees the new sample)
            interval = float(t[1] - t[0]) if t.numel() > 1 else 0.0
            check_fixed_steps(self.name, delay_substeps(interval, 1e-3, delay), interval, self.dt)
            return rk4_delay(
                lambda tt, xx, hist: self.rhs(tt, xx, signal(tt), history=hist), x0, t, step=1e-3, min_delay=delay
            )
        options: dict[str, Any] = {"max_num_steps": GROUND_TRUTH_MAX_STEPS} if method in ADAPTIVE else {}
        if method in ADAPTIVE and t.numel() > 2:  # step to every sample time: the input jumps (zoh) or bends there
            options["jump_t" if signal.hold == "zoh" else "step_t"] = t[1:-1]
        x = odeint(
            lambda tt, xx: self.rhs(tt, xx, signal(tt)), x0, t, rtol=rtol, atol=atol, method=method, options=options
        )
        return x.transpose(0, 1)

    def _simulate(self, x0, t, rtol, atol, method) -> Trajectories:
        if self.integrator == "dopri5":
            return super()._simulate(x0, t, rtol, atol, method)
        assert self.substep is not None  # _integrator requires it for semi_implicit_euler
        x = semi_implicit_euler(self.rhs, self._kinematic_mask(x0), x0, t, self.substep, self._steps_per_interval(t))
        return Trajectories(t=t, x=x, edge_index=self.edge_index, meta=self.meta(grid_step(t)))

    def _kinematic_mask(self, x: torch.Tensor) -> torch.Tensor:  # x: [B, N, D]
        """[D] bool: True on the kinematic rows (updated second, from the new dynamic rows)."""
        return torch.tensor([s in self.spec.kinematic for s in self.spec.states], device=x.device)

    def sample_initial_states(self, n: int, generator: torch.Generator) -> torch.Tensor:
        r = torch.rand(n, self.n_nodes, self.spec.state_dim, generator=generator, dtype=torch.float64)
        lo, hi = self.ranges[:, 0], self.ranges[:, 1]
        return lo + (hi - lo) * r


def semi_implicit_euler(
    rhs,
    kinematic: torch.Tensor,  # [D] bool: rows updated second, with the new dynamic rows
    x0: torch.Tensor,  # [B, N, D] initial states
    t: torch.Tensor,  # [T] output times
    h: float,
    steps: list[int],  # Euler steps between consecutive output times (T − 1 entries)
) -> torch.Tensor:
    """[B, T, N, D] symplectic Euler: each step v ← v + h·f_v(t, x, v), then x ← x + h·f_x(t, x, v_new).

    `rhs(t, x) -> [B, N, D]` is the full right-hand side; each half step keeps only its own rows of it.
    """
    x, out = x0, [x0]
    for i, n_steps in enumerate(steps):  # a loop in time only; every step is vectorised over B, N and D
        for k in range(n_steps):
            tk = t[i] + k * h
            x = torch.where(kinematic, x, x + h * rhs(tk, x))
            x = torch.where(kinematic, x + h * rhs(tk, x), x)
        out.append(x)
    return torch.stack(out, dim=1).contiguous()
