"""`equations`: a white-box model whose equations are written in the config (`mpsim.equations`), no Python.

    mpsim train model=equations model.spec=my_pendulums.yaml data.path=measured.npz

The spec's learnable parameters are trained by the same trainer as any model (full-rollout shooting through
the model's ODE solver); the rest stay fixed. Neighbour terms run over the data's own graph (one per trajectory
where the data has several). The spec is plain data inside the checkpoint, so finetune, eval and zero-shot work
as for any model, and `mpsim diagnose` reads the parameters' sensitivities and the kinematic rows.

A driven spec (`inputs: [u, ...]`) reads the data's controls, matched by name (the data's `control_names` must be
the spec's inputs, in order), in physical units, held between samples as the data's `meta["input_hold"]` says
(`linear` by default, or `zoh`; see `mpsim.models.driving`).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import replace
from typing import Any, cast

import torch
from torch import nn

from mpsim.data.trajectories import Inputs
from mpsim.effects import Effect, EffectContext, min_delay, total
from mpsim.effects.inputs import record_index, through_all
from mpsim.errors import ConfigError, IncompatibleError
from mpsim.graphs.batch import BatchedGraph, batch_graph
from mpsim.models.base import Model
from mpsim.models.capabilities import one_step_by_rollouts
from mpsim.models.controls import HeldField, integrate_held
from mpsim.models.driving import (
    GridInput,
    IntervalInput,
    check_input_count,
    check_input_names,
    input_hold,
)
from mpsim.solvers.odeint import ODESolver
from mpsim.spec import SYSTEM_KEYS, EquationField, Spec, check_nodes, check_states, merge_spec, parse_spec

ENTRY = re.compile(r"^(?P<name>\w+)\[(?P<i>\d+)\]$")


class _Field(HeldField):
    """The spec's field (plus effects) of one rollout; `signal` gives the inputs at the solver's time (None: the
    spec has none). `u` and `held` are what `integrate_held` reads and sets (zero-order-hold inputs)."""

    def __init__(
        self,
        model: EquationsModel,
        values: dict[str, torch.Tensor],
        graph: BatchedGraph | None,
        offset: torch.Tensor | None = None,  # [B, 1] start time of each sample (one-step batches), else None
        signal: GridInput | IntervalInput | None = None,
        records: torch.Tensor | None = None,  # [B] each row's recording (a per-recording input gain), else None
    ) -> None:
        super().__init__()
        self.model, self.values, self.graph, self.offset, self.signal = model, values, graph, offset, signal
        self.records = records
        self.u = signal.u if isinstance(signal, GridInput) and signal.hold == "zoh" else None
        # fixed for the rollout: sorted once, not at every evaluation of the field
        self.terms, self.drifting = model.terms(), bool(model.drifts())
        self.gains = model.input_gains()

    @property
    def held(self) -> int | None:
        return self.signal.held if isinstance(self.signal, GridInput) else None

    @held.setter
    def held(self, k: int | None) -> None:
        if isinstance(self.signal, GridInput):
            self.signal.held = k

    def forward(self, t: torch.Tensor, x: torch.Tensor, history=None) -> torch.Tensor:  # x: [B, N, D] raw
        u = None if self.signal is None else self.signal(t)  # [B, N, C] at the solver's (local) time
        if u is not None and self.gains:
            u = through_all(self.model.input_gains(), self.model.spec.inputs, u, self.records)
        if self.offset is not None:
            t = t + self.offset
        values = self.model.drifted(self.values, t) if self.drifting else self.values
        dx = self.model.field(t, x, values, self.graph, u)
        if self.terms:
            assert self.graph is not None  # `EquationsModel._graph` builds it whenever there are effects
            dx = dx + total(self.terms, t, x, EffectContext(self.graph, history))
        return dx


class EquationsModel(Model):
    """Equations from a spec, with the spec's learnable parameters trainable (plus optional learnable effects).

    Args:
        state_dim, control_dim: set from the data (the spec's states must match the data's, and its inputs the
            data's controls).
        spec: the spec as a mapping (`model.spec=<file>` is loaded by the command layer).
        states, inputs, equations, params, learnable, kinematic, nodes, shift_boundary: the same keys inline (they
            override `spec`'s).
        init: starting values {name: value} of learnable parameters (default: the spec's values).
        effects: extra named terms with learnable coefficients.
        solver: ODE solver of the rollouts.
    """

    def __init__(
        self,
        state_dim: int,
        control_dim: int = 0,
        spec: dict[str, Any] | None = None,
        states: list[str] | None = None,
        inputs: list[str] | None = None,
        equations: dict[str, Any] | None = None,
        params: dict[str, Any] | None = None,
        learnable: list[str] | None = None,
        kinematic: list[str] | None = None,
        nodes: int | None = None,
        shift_boundary: str | float | None = None,
        init: dict[str, Any] | None = None,
        effects: Sequence[Effect] = (),
        solver: ODESolver | None = None,
    ) -> None:
        super().__init__(state_dim, control_dim, effects)
        inline = {
            "states": states,
            "inputs": inputs,
            "equations": equations,
            "params": params,
            "learnable": learnable,
            "kinematic": kinematic,
            "nodes": nodes,
            "shift_boundary": shift_boundary,
        }
        self.spec: Spec = parse_spec(merge_spec(spec, inline, "model"), "model.spec", extra_keys=SYSTEM_KEYS)
        if len(self.spec.columns) != state_dim:
            outputs = f" and {len(self.spec.outputs)} outputs {list(self.spec.outputs)}" if self.spec.outputs else ""
            raise ConfigError(
                f"model.spec has {self.spec.state_dim} states {list(self.spec.states)}{outputs} but the data "
                f"has {state_dim} per node."
            )
        check_input_count(self.spec.inputs, control_dim)
        self.field = EquationField(self.spec)
        self.output_field = EquationField(self.spec, outputs=True) if self.spec.outputs else None
        self.solver = solver or ODESolver()
        values = dict(self.spec.params)
        for name, value in (init or {}).items():
            if name not in self.spec.learnable:
                raise ConfigError(
                    f"model.init.{name}: not a learnable parameter; learnable: {list(self.spec.learnable)}."
                )
            start = torch.as_tensor(value, dtype=torch.float64)
            if start.shape != values[name].shape:
                raise ConfigError(
                    f"model.init.{name} has shape {list(start.shape)}; the spec's value has {list(values[name].shape)}."
                )
            values[name] = start
        # positive constants are trained in log space so they stay positive (as model=physics)
        self.positive = [n for n in self.spec.learnable if bool((values[n] > 0).all())]
        self.raw = nn.ParameterDict(
            {n: nn.Parameter(values[n].log() if n in self.positive else values[n].clone()) for n in self.spec.learnable}
        )
        self.fixed = [n for n in self.spec.params if n not in self.spec.learnable]
        for n in self.fixed:
            self.register_buffer(f"fixed_{n}", values[n].clone())
        self.kinematic_states = list(self.spec.kinematic)

    # ---- parameters ---------------------------------------------------------------------------------------
    def parameters_now(self) -> dict[str, torch.Tensor]:
        """{name: current value} of every spec parameter (learnable ones as trained)."""
        out = {n: (p.exp() if n in self.positive else p) for n, p in self.raw.items()}
        out.update({n: getattr(self, f"fixed_{n}") for n in self.fixed})
        return out

    def drifts(self) -> list[Effect]:
        """The carried `ParameterDrift` effects: p(t) = p·(1 + s·t) of a spec parameter (t: the data's time)."""
        return [e for e in self.effects if getattr(e, "acts_on_parameters", False)]

    def terms(self) -> list[Effect]:
        """The carried effects that add a term to dx/dt (all but the parameter drifts and input gains)."""
        return [
            e
            for e in self.effects
            if not getattr(e, "acts_on_parameters", False) and not getattr(e, "acts_on_inputs", False)
        ]

    def input_gains(self) -> list[Effect]:
        """The carried input-path effects (`InputGain`, `DeadZone`, `InputSaturation`), in the order u meets them."""
        return [e for e in self.effects if getattr(e, "acts_on_inputs", False)]

    def drifted(
        self,
        values: dict[str, torch.Tensor],  # name -> [] / [N] / [N·D, N·D] nominal value
        t: torch.Tensor,  # [] time (or [M, 1] one per state)
    ) -> dict[str, torch.Tensor]:
        """The parameters at time t: each drifting one multiplied by 1 + s·t (a scalar parameter becomes [M, 1]
        when t is one time per state; the field broadcasts it as it does t)."""
        drifts = self.drifts()
        if not drifts:
            return values
        out = dict(values)
        for e in drifts:  # a handful of named drifts
            name = cast(Any, e).param
            out[name] = out[name] * cast(Any, e).factor(torch.as_tensor(t, dtype=out[name].dtype))
        return out

    # ---- checks -------------------------------------------------------------------------------------------
    def bind_effects(self, state_names: Sequence[str]) -> None:
        """Check the data's state names against the spec's, then resolve the effects' names (and check that
        each parameter drift names a scalar parameter of the spec, once)."""
        check_states(self.spec, state_names, "model.spec")
        super().bind_effects(state_names)
        seen: set[str] = set()
        for e in self.drifts():
            name = cast(Any, e).param
            if name not in self.spec.params or self.spec.params[name].dim() != 0:
                scalars = [n for n, v in self.spec.params.items() if v.dim() == 0]
                raise ConfigError(
                    f"model.effects: ParameterDrift(param={name!r}) must name a scalar parameter of the spec; "
                    f"scalars: {scalars}."
                )
            if name in seen:
                raise ConfigError(f"model.effects: two ParameterDrift effects of {name!r}; keep one.")
            seen.add(name)
        for e in self.input_gains():
            if not self.spec.inputs:
                raise ConfigError(
                    f"model.effects: {type(e).__name__} acts on an input, but model.spec declares no inputs:."
                )
            cast(Any, e).channel(self.spec.inputs)

    def bind_inputs(self, control_names: Sequence[str]) -> None:
        """Check the data's control names against the spec's inputs (same names, same order).

        Raises:
            ConfigError: one message naming both lists and `data.control_columns` / `data.columns` as the fix.
        """
        check_input_names(self.spec.inputs, control_names)

    def check_compatible(
        self, state_dim: int, control_dim: int, n_nodes: int, trained_nodes: int | None = None
    ) -> None:
        try:
            check_input_count(self.spec.inputs, control_dim)
            check_nodes(self.spec, n_nodes, "model.spec")
        except ConfigError as err:
            raise IncompatibleError(str(err)) from None
        super().check_compatible(state_dim, control_dim, n_nodes, None)

    @property
    def time_invariant(self) -> bool:
        """The spec reads no `t` and no effect a drive: a window's rollout does not depend on where it starts."""
        return not self.spec.uses_time and not any(e.uses_time for e in self.effects)

    # ---- rollout ------------------------------------------------------------------------------------------
    def rollout(
        self,
        x0: torch.Tensor,  # [B, N, D] initial states (raw units; with outputs, D = states + outputs)
        t: torch.Tensor,  # [T] times
        inputs: Inputs,  # the data's graph [2, E] or [B, 2, E], controls [B, T, N, C] on the grid t, meta
    ) -> torch.Tensor:
        """[B, T, N, D] the spec integrated from x0; a driven spec reads `inputs.u` held as
        `inputs.meta["input_hold"]` says (zoh: no solver step straddles a sample time, see `mpsim.models.driving`).
        A spec with `outputs:` integrates its states and appends what its sensors read at every time."""
        if self.output_field is None:
            return self._rollout(x0, t, inputs)
        if inputs.past is not None:  # a delayed effect's history: the states, not what the sensors read
            inputs = replace(inputs, past=inputs.past[..., : self.spec.state_dim])
        xs = self._rollout(x0[..., : self.spec.state_dim], t, inputs)
        return torch.cat([xs, self.outputs_of(xs, t, inputs)], dim=-1)

    def outputs_of(
        self,
        xs: torch.Tensor,  # [B, T, N, D_s] states (raw units), the spec's states only
        t: torch.Tensor,  # [T] their times
        inputs: Inputs,  # controls [B, T, N, C] on the grid t
    ) -> torch.Tensor:
        """[B, T, N, P] what the spec's sensors read (`outputs:`) at each time, from the states and the inputs
        at the samples."""
        assert self.output_field is not None
        b, n_t, n, d = xs.shape
        values = {k: v.to(xs) for k, v in self.parameters_now().items()}
        u = None
        if self.spec.inputs:
            rows = record_index(inputs.meta, b).repeat_interleave(n_t)  # [B·T] recording-major
            u = self._signal(xs[:, 0], t, inputs).u.reshape(b * n_t, n, -1)  # type: ignore[union-attr]
            u = through_all(self.input_gains(), self.spec.inputs, u, rows)
        tt = t.to(xs).repeat(b)[:, None]  # [B·T, 1] each row's time
        out = self.output_field(tt, xs.reshape(b * n_t, n, d), values, None, u)
        return out.reshape(b, n_t, n, -1)

    def _rollout(
        self,
        x0: torch.Tensor,  # [B, N, D_s] initial states (raw units), the spec's states only
        t: torch.Tensor,  # [T] times
        inputs: Inputs,  # the data's graph [2, E] or [B, 2, E], controls [B, T, N, C] on the grid t, meta
    ) -> torch.Tensor:
        """[B, T, N, D_s] the spec's states integrated from x0 (`rollout`)."""
        check_nodes(self.spec, x0.shape[1], "model.spec")
        values = {k: v.to(x0) for k, v in self.parameters_now().items()}
        signal = self._signal(x0, t, inputs)
        records = inputs.meta.get("record_index") if self.input_gains() else None
        field = _Field(self, values, self._graph(inputs.edge_index, x0), signal=signal, records=records)
        if field.u is not None and min_delay(self.effects) == 0:  # zero-order hold: no step straddles a jump
            if getattr(self.solver, "restarts", False):  # dopri5 steps to every sample and restarts there
                return self.solver(field, x0, t, restart=True)
            return integrate_held(lambda f, y, tt: self.integrate(f, y, tt, self.solver), field, x0, t)
        return self.integrate(field, x0, t, self.solver, inputs.past)

    def _signal(self, x0: torch.Tensor, t: torch.Tensor, inputs: Inputs) -> GridInput | None:  # x0: [B, N, D]
        """The rollout's inputs on its grid (None for a spec without inputs), checked against the spec by name
        (the data's `control_names`, where the data name them) and by shape."""
        names = inputs.meta.get("control_names")
        if names:
            check_input_names(self.spec.inputs, list(names))
        elif inputs.u is not None:
            check_input_count(self.spec.inputs, inputs.u.shape[-1])
        if not self.spec.inputs:
            return None
        u, want = inputs.u, (x0.shape[0], t.numel(), x0.shape[1], self.spec.input_dim)
        if u is None or tuple(u.shape) != want:
            got = "no controls" if u is None else f"controls of shape {list(u.shape)}"
            raise ConfigError(
                f"model.spec.inputs {list(self.spec.inputs)} need the controls [B, T, N, C] = {list(want)} on the "
                f"rollout's grid; got {got}."
            )
        return GridInput(t.to(x0), u.to(x0), input_hold(inputs.meta))

    def one_step(
        self,
        x: torch.Tensor,  # [B, T, N, D] observed states (raw units)
        t: torch.Tensor,  # [T] times
        inputs: Inputs,  # the data's graph [2, E] or [B, 2, E], controls [B, T, N, C] on the grid t, meta
    ) -> torch.Tensor:
        """[B, T−1, N, D] one step from every observed state, all steps in one batched integration (the
        equations have no latent state; each sample keeps its absolute start time and its own input interval).
        Falls back to one step at a time for delayed effects (they read a history) and per-recording drives. With
        `outputs:`, the step is of the states and the outputs are read at each step's end."""
        if self._by_rollouts(t):
            return one_step_by_rollouts(self, x, t, inputs)
        if self.output_field is not None:
            xs = self._one_step(x[..., : self.spec.state_dim], t, inputs)
            return torch.cat([xs, self.outputs_of(xs, t[1:], _after_first(inputs))], dim=-1)
        return self._one_step(x, t, inputs)

    def _by_rollouts(self, t: torch.Tensor) -> bool:  # t: [T] times
        """Whether one steps are taken one at a time (a grid that is not uniform, delayed effects: they read a
        history, per-recording drives, a drifting parameter in a neighbour sum) rather than in one batch."""
        dts = t[1:] - t[:-1]
        uniform = t.numel() > 1 and bool((dts - dts[0]).abs().max() <= 1e-9 * dts[0].abs().clamp(min=1e-300))
        special = min_delay(self.effects) > 0 or any(e.per_record and e.uses_time for e in self.effects)  # a phase
        special = special or bool(self.drifts() and self.field.uses_graph)  # a [M, 1] parameter in a neighbour sum
        return not uniform or special

    def _one_step(
        self,
        x: torch.Tensor,  # [B, T, N, D_s] states (raw units)
        t: torch.Tensor,  # [T] times
        inputs: Inputs,  # the data's graph, controls [B, T, N, C] on the grid t, meta
    ) -> torch.Tensor:
        """[B, T−1, N, D_s] `one_step` of the spec's states."""
        b, n_t, n, d = x.shape
        dts = t[1:] - t[:-1]
        x0 = x[:, :-1].reshape(b * (n_t - 1), n, d)
        offset = t[:-1].to(x).repeat(b)[:, None]  # [B·(T−1), 1]
        edge_index = inputs.edge_index
        ei = edge_index if edge_index.dim() == 2 else edge_index.repeat_interleave(n_t - 1, dim=0)
        check_nodes(self.spec, n, "model.spec")
        values = {k: v.to(x) for k, v in self.parameters_now().items()}
        grid = self._signal(x[:, 0], t, inputs)
        signal = None
        if grid is not None:
            u0 = grid.u[:, :-1].reshape(b * (n_t - 1), n, -1)  # [B·(T−1), N, C] each interval's first sample
            du = None if grid.hold == "zoh" else (grid.u[:, 1:] - grid.u[:, :-1]).reshape(u0.shape)
            signal = IntervalInput(u0, du, dts[0].to(x))
        records = record_index(inputs.meta, b).repeat_interleave(n_t - 1) if self.input_gains() else None
        field = _Field(self, values, self._graph(ei, x0), offset, signal, records)
        local = torch.stack([torch.zeros_like(dts[0]), dts[0]]).to(x)
        return self.integrate(field, x0, local, self.solver)[:, 1].reshape(b, n_t - 1, n, d)

    def _graph(self, edge_index: torch.Tensor, x: torch.Tensor) -> BatchedGraph | None:  # x: [B, N, D]
        if not (self.field.uses_graph or len(self.effects)):
            return None
        return batch_graph(edge_index.to(x.device), x.shape[0], x.shape[1], dtype=x.dtype)

    # ---- what the residual loop reads ---------------------------------------------------------------------
    def _entries(self) -> list[tuple[str, str, int | None]]:
        """(label, parameter, index) of every learnable scalar and per-node entry (matrices are left out)."""
        out: list[tuple[str, str, int | None]] = []
        for n in self.spec.learnable:
            v = self.spec.params[n]
            if v.dim() == 0:
                out.append((n, n, None))
            elif v.dim() == 1:
                out += [(f"{n}[{i}]", n, i) for i in range(v.numel())]
        return out

    def sensitivities(
        self,
        t: torch.Tensor,  # [M, 1] or [] times
        x: torch.Tensor,  # [M, N, D] states (raw units)
        edge_index: torch.Tensor,  # [2, E] graph
        u: torch.Tensor | None = None,  # [M, N, C] the inputs with those states (a driven spec needs them)
    ) -> torch.Tensor | None:
        """[M, N, D, P] ∂f/∂p of the equations at the given states (and inputs) for every learnable scalar and
        per-node entry (one forward-mode derivative each; matrix parameters are left out)."""
        if self.spec.inputs and u is None:
            raise ConfigError(
                f"model.spec.inputs {list(self.spec.inputs)}: the sensitivities of a driven spec need the inputs "
                "[M, N, C] with the states (u=...)."
            )
        u = None if u is None else u.to(x)
        values = {n: v.detach().to(x) for n, v in self.parameters_now().items()}
        graph = self._graph(edge_index, x) if self.field.uses_graph else None
        columns = []
        for _, name, index in self._entries():  # a loop over the spec's few parameters
            tangent = torch.zeros_like(values[name])
            if index is None:
                tangent.fill_(1.0)
            else:
                tangent[index] = 1.0

            def f(v: torch.Tensor, name: str = name) -> torch.Tensor:  # v: the nominal value (drifts applied)
                return self.field(t, x, self.drifted({**values, name: v}, t), graph, u)

            columns.append(torch.func.jvp(f, (values[name],), (tangent,))[1])
        if not columns:
            return None
        return torch.stack(columns, dim=-1)

    def input_sensitivity(
        self,
        t: torch.Tensor,  # [M, 1] or [] times
        x: torch.Tensor,  # [M, N, D] states (raw units)
        edge_index: torch.Tensor,  # [2, E] graph
        u: torch.Tensor,  # [M, N, C] the inputs with those states
        direction: torch.Tensor,  # [M, N, C] a change of the inputs
    ) -> torch.Tensor:
        """[M, N, D] ∂f/∂u·δu, the field's first-order change when the inputs change by δu = `direction`."""
        u = u.to(x)
        values = {n: v.detach().to(x) for n, v in self.parameters_now().items()}
        graph = self._graph(edge_index, x) if self.field.uses_graph else None

        def f(v: torch.Tensor) -> torch.Tensor:  # v: [M, N, C] the inputs
            return self.field(t, x, self.drifted(values, t), graph, v)

        return torch.func.jvp(f, (u,), (direction.to(x),))[1]

    def sensitivity_names(self) -> list[str]:
        return [label for label, _, _ in self._entries()]

    def shift_parameters(self, shifts: dict[str, float]) -> None:
        current = self.parameters_now()
        with torch.no_grad():
            for label, delta in shifts.items():
                m = ENTRY.match(label)
                name, index = (m["name"], int(m["i"])) if m else (label, None)
                if name not in self.raw:
                    continue
                value = current[name].detach().clone()
                if index is None:
                    value = value + delta
                else:
                    value[index] += delta
                if name in self.positive:
                    if bool((value <= 0).any()):
                        continue  # a shift that would flip the sign of a positive constant is not applied
                    value = value.log()
                self.raw[name].copy_(value.to(self.raw[name]))

    def report(self) -> dict[str, Any]:
        values = {n: _plain(v) for n, v in self.parameters_now().items() if n in self.raw}
        return {
            "physical_parameters": values,
            "equations": self.spec.equation_text(),
            **({"inputs": list(self.spec.inputs)} if self.spec.inputs else {}),
            "kinematic": self.kinematic_states,
            "effects": [e.describe() for e in self.effects],
        }

    def report_lines(self) -> list[tuple[str, str]]:
        values = ", ".join(f"{n}={_short(v)}" for n, v in self.parameters_now().items() if n in self.raw)
        rows = [("fitted parameters", values or "(none learnable)")]
        rows += [("effect", e.describe()) for e in self.effects]
        return rows


def _plain(v: torch.Tensor) -> Any:
    v = v.detach()
    return float(v) if v.dim() == 0 else v.cpu().tolist()


def _short(v: torch.Tensor) -> str:
    if v.dim() == 0:
        return f"{float(v.detach()):.5g}"
    flat = v.detach().flatten().tolist()
    body = ", ".join(f"{x:.4g}" for x in flat[:8]) + (", ..." if len(flat) > 8 else "")
    return f"[{body}]"


def _after_first(inputs: Inputs) -> Inputs:
    """`inputs` without their first sample (the controls at the ends of one-step intervals)."""
    return replace(inputs, u=None if inputs.u is None else inputs.u[:, 1:])
