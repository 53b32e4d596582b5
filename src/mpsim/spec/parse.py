"""A spec as plain data → a checked `Spec` (states, parsed right-hand sides, parameter values, what is learnable)."""

from __future__ import annotations

import keyword
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import sympy
import torch

from mpsim.errors import ConfigError, did_you_mean
from mpsim.spec.grammar import DEG, LIN, MEAN_NBR, NEIGHBOUR_SUFFIX, RESERVED, SHIFT, SUM_NBR, Parser, T

#: spec keys every spec may have; systems add their own (initial ranges, graph, ...)
MODEL_KEYS = (
    "states",
    "inputs",
    "outputs",
    "equations",
    "params",
    "learnable",
    "kinematic",
    "nodes",
    "shift_boundary",
    "description",
)
#: what `shift(x, k)` reads beyond the first and last node besides a number (`shift_boundary`)
SHIFT_BOUNDARIES = ("wrap", "edge")
#: what a simulation also needs (`system=equations`); a model reads the same file and ignores them
SYSTEM_KEYS = (
    "name",
    "graph",
    "graph_params",
    "edges",
    "directed",
    "init",
    "dt",
    "horizon",
    "integrator",
    "substep",
    "input",
)


@dataclass(frozen=True)
class Spec:
    """A parsed, checked spec.

    Attributes:
        states: D state names per node, in the data's column order.
        rhs: one sympy expression per state (d state / dt).
        params: name -> float64 value: [] scalar, [N] per node, or [N·D, N·D] matrix (used through `lin`).
        learnable: parameter names that training fits.
        kinematic: states whose equation is another state (θ̇ = ω) or that the spec declares so.
        n_nodes: N when the spec fixes it (a per-node or matrix parameter, or `nodes:`), else None.
        raw: the spec as plain data (what checkpoints store).
        where: the config key it was given as (messages name it).
        inputs: C input names per node (`inputs:`): values the data give (its controls, matched by name), used
            in the equations like states but with no equation of their own.
        shift_boundary: what `shift(x, k)` reads at a node i + k beyond the ends (0..N−1): "wrap" (node
            (i + k) mod N, a ring), "edge" (the nearest end node's value) or a number; the spec's `shift_boundary`,
            else "wrap" when its graph is `ring`, else None (the spec uses no shift).
        outputs: P names of what the sensors read (`outputs: {y: abs(s)}`), in the spec's order; the data's
            measured columns of those names are compared with them, and a model's rollout appends them to its
            states (the data's columns are the states, then the outputs).
        output_exprs: one sympy expression per output, of the states, inputs, parameters and t.
    """

    states: tuple[str, ...]
    rhs: tuple[sympy.Expr, ...]
    params: dict[str, torch.Tensor]
    learnable: tuple[str, ...]
    kinematic: tuple[str, ...]
    n_nodes: int | None
    raw: dict[str, Any] = field(repr=False)
    where: str = "model.spec"
    inputs: tuple[str, ...] = ()
    shift_boundary: str | float | None = None
    outputs: tuple[str, ...] = ()
    output_exprs: tuple[sympy.Expr, ...] = ()

    @property
    def state_dim(self) -> int:
        return len(self.states)

    @property
    def columns(self) -> tuple[str, ...]:
        """The data's columns for this spec: its states, then its outputs."""
        return (*self.states, *self.outputs)

    @property
    def input_dim(self) -> int:
        return len(self.inputs)

    @property
    def uses_time(self) -> bool:
        """Whether an equation or an output reads the time `t` (a drive written into the spec)."""
        return any(T in e.free_symbols for e in (*self.rhs, *self.output_exprs))

    def rates(self) -> dict[str, str]:
        """{s: o} for every equation ``o' = s`` that is another state (a velocity is the rate of a position):
        how a state that is not measured is estimated from one that is."""
        return {
            str(rhs): o
            for o, rhs in zip(self.states, self.rhs, strict=True)
            if rhs.is_Symbol and str(rhs) in self.states
        }

    def equation_text(self) -> dict[str, str]:
        return {s: str(e) for s, e in zip(self.states, self.rhs, strict=True)}


def _names(value: Any, key: str, where: str) -> list[str]:
    if value is None:
        return []
    if isinstance(value, str) or not isinstance(value, Sequence) or not all(isinstance(v, str) for v in value):
        raise ConfigError(f"{where}.{key} must be a list of names, e.g. [theta, omega]; got {value!r}.")
    return list(value)


def _check_name(name: str, where: str, what: str) -> None:
    if not name.isidentifier() or keyword.iskeyword(name):
        raise ConfigError(
            f"{where}: {what} name {name!r} is not a valid identifier (letters, digits, _; not a "
            "Python keyword such as lambda). Rename it."
        )
    if name in RESERVED:
        raise ConfigError(f"{where}: {what} name {name!r} is reserved (t, deg, pi and the function names). Rename it.")
    if name.endswith(NEIGHBOUR_SUFFIX):
        raise ConfigError(f"{where}: {what} name {name!r} ends in '_j', which denotes a neighbour's value. Rename it.")


def _param_value(name: str, value: Any, where: str) -> torch.Tensor:
    def bad() -> ConfigError:
        return ConfigError(
            f"{where}.params.{name}: expected a number, a list of numbers (one per node) or a "
            f"square matrix (list of rows); got {str(value)[:80]!r}."
        )

    def number(v: Any) -> bool:
        return isinstance(v, int | float) and not isinstance(v, bool)

    if number(value):
        out = torch.tensor(float(value), dtype=torch.float64)
    elif isinstance(value, Sequence) and not isinstance(value, str) and len(value) > 0:
        if all(number(v) for v in value):
            out = torch.tensor([float(v) for v in value], dtype=torch.float64)
        elif all(isinstance(r, Sequence) and not isinstance(r, str) and all(number(v) for v in r) for r in value):
            if len({len(r) for r in value}) != 1 or len(value[0]) != len(value):
                raise ConfigError(
                    f"{where}.params.{name}: a matrix parameter must be square; got "
                    f"{len(value)} rows of lengths {sorted({len(r) for r in value})}."
                )
            out = torch.tensor([[float(v) for v in r] for r in value], dtype=torch.float64)
        else:
            raise bad()
    else:
        raise bad()
    if not torch.isfinite(out).all():
        raise ConfigError(f"{where}.params.{name} has a NaN or infinite value; give finite numbers.")
    return out


def merge_spec(spec: Mapping[str, Any] | None, inline: Mapping[str, Any], where: str) -> dict[str, Any]:
    """The spec from `spec` with the keys given inline on top (inline keys win)."""
    if isinstance(spec, str):
        raise ConfigError(
            f"{where}.spec={spec!r} is a file name, but specs are read by the command layer "
            "(`mpsim ... model.spec=<file>`); in Python pass the loaded mapping "
            "(mpsim.spec.load_spec_file)."
        )
    if spec is not None and not isinstance(spec, Mapping):
        raise ConfigError(f"{where}.spec must be a mapping or a YAML file name; got {type(spec).__name__}.")
    merged = dict(spec or {})
    merged.update({k: v for k, v in inline.items() if v is not None})
    if not merged:
        raise ConfigError(
            f"{where}: no equations. Pass {where}.spec=<file.yaml> or {where}.states / "
            f"{where}.equations / {where}.params inline (see docs/equations.md)."
        )
    return merged


def parse_spec(spec: Mapping[str, Any], where: str = "model.spec", extra_keys: Sequence[str] = ()) -> Spec:
    """Check a spec and parse its equations.

    Args:
        spec: the plain spec (see the module docstring).
        where: the config path named in error messages.
        extra_keys: further top-level keys the caller understands (e.g. a system's initial ranges).

    Raises:
        ConfigError: one message naming what is wrong and where.
    """
    if not isinstance(spec, Mapping):
        raise ConfigError(f"{where} must be a mapping with states, equations and params; got {type(spec).__name__}.")
    allowed = (*MODEL_KEYS, *extra_keys)
    for key in spec:
        if key not in allowed:
            raise ConfigError(
                f"{where}.{key} is not a spec key.{did_you_mean(str(key), allowed)} Valid keys: {', '.join(allowed)}."
            )
    states = _names(spec.get("states"), "states", where)
    if not states:
        raise ConfigError(f"{where}.states is missing: list the per-node state names in the data's column order.")
    if len(set(states)) != len(states):
        raise ConfigError(f"{where}.states lists a name twice: {states}.")
    for s in states:
        _check_name(s, where, "state")
    inputs = _inputs(spec.get("inputs"), states, where)
    raw_params = spec.get("params") or {}
    if not isinstance(raw_params, Mapping):
        raise ConfigError(f"{where}.params must be a mapping name: value; got {type(raw_params).__name__}.")
    params: dict[str, torch.Tensor] = {}
    for name, value in raw_params.items():
        _check_name(str(name), where, "parameter")
        if name in states or name in inputs:
            what = "a state" if name in states else "an input"
            raise ConfigError(f"{where}.params.{name} has the name of {what}; rename the parameter.")
        params[str(name)] = _param_value(str(name), value, where)
    n_nodes = _node_count(spec.get("nodes"), params, len(states), where)

    equations = _equations(spec.get("equations"), states, inputs, where)
    parser = Parser(states, params, where, inputs)
    rhs = tuple(parser.parse(s, equations[s]) for s in states)
    outputs, output_exprs = _outputs(spec.get("outputs"), parser, [*states, *inputs, *params], where)
    shift_boundary = _shift_boundary(spec, [*states, *outputs], (*rhs, *output_exprs), where)

    learnable = list(params) if spec.get("learnable") is None else _names(spec.get("learnable"), "learnable", where)
    for name in learnable:
        if name not in params:
            raise ConfigError(
                f"{where}.learnable names {name!r}, which is not a parameter."
                f"{did_you_mean(name, list(params))} Parameters: {sorted(params)}."
            )
    auto = [s for s, e in zip(states, rhs, strict=True) if isinstance(e, sympy.Symbol) and e.name in states]
    kinematic = auto if spec.get("kinematic") is None else _names(spec.get("kinematic"), "kinematic", where)
    for name in kinematic:
        if name not in states:
            raise ConfigError(f"{where}.kinematic names {name!r}, which is not a state.{did_you_mean(name, states)}")
    plain = {k: _plain(v) for k, v in spec.items()}
    return Spec(
        tuple(states),
        rhs,
        params,
        tuple(learnable),
        tuple(kinematic),
        n_nodes,
        plain,
        where,
        tuple(inputs),
        shift_boundary,
        tuple(outputs),
        tuple(output_exprs),
    )


def _outputs(outputs: Any, parser: Parser, taken: list[str], where: str) -> tuple[list[str], list[sympy.Expr]]:
    """The spec's `outputs: {name: expression}`: what the sensors read, as expressions of the states, inputs,
    parameters and t (neighbour sums are not allowed: an output is read at one node)."""
    if outputs is None:
        return [], []
    if not isinstance(outputs, Mapping) or not outputs:
        raise ConfigError(
            f"{where}.outputs must map each measured name to what the sensor reads, e.g. outputs: {{y: abs(s)}}; got "
            f"{outputs!r}."
        )
    names, exprs = [], []
    for name, text in outputs.items():
        _check_name(str(name), where, "output")
        if name in taken:
            raise ConfigError(
                f"{where}.outputs.{name}: {name!r} is already a state, input or parameter; give the output a name "
                "of its own (the file's column is mapped to it with data.columns)."
            )
        expr = parser.parse(str(name), text, key="outputs")
        if any(expr.has(f) for f in (SUM_NBR, MEAN_NBR, DEG, LIN)):
            raise ConfigError(
                f"{where}.outputs.{name}: an output is what one node's sensor reads; neighbour terms (sum_nbr, "
                "mean_nbr, deg, lin) are not allowed in it."
            )
        names.append(str(name))
        exprs.append(expr)
    return names, exprs


def _equations(equations: Any, states: list[str], inputs: list[str], where: str) -> Mapping[str, Any]:
    """The spec's `equations`: one per state, none for an input or an unknown name."""
    if not isinstance(equations, Mapping):
        raise ConfigError(f"{where}.equations is missing: give one expression per state, e.g. {{{states[0]}: ...}}.")
    for key in equations:
        if key in inputs:
            raise ConfigError(
                f"{where}.equations.{key}: {key!r} is an input (its values come from the data's controls), not a "
                "state; inputs have no equation. Remove it, or list it under states."
            )
        if key not in states:
            raise ConfigError(
                f"{where}.equations.{key}: {key!r} is not a state.{did_you_mean(str(key), states)} States: {states}."
            )
    missing = [s for s in states if s not in equations]
    if missing:
        raise ConfigError(f"{where}.equations has no equation for {missing}; give d/dt of every state.")
    return equations


def _shift_boundary(
    spec: Mapping[str, Any], states: list[str], rhs: Sequence[sympy.Expr], where: str
) -> str | float | None:
    """What shift(x, k) reads beyond the first and last node: the spec's `shift_boundary`, else wrap on a ring.

    Raises:
        ConfigError: a value that is not wrap, edge or a finite number; or equations with shift and neither a
            stated boundary nor `graph: ring`.
    """
    value = spec.get("shift_boundary")
    if value is not None:
        if value in SHIFT_BOUNDARIES:
            return str(value)
        if isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value):
            return float(value)
        raise ConfigError(
            f"{where}.shift_boundary must be wrap (node N−1's next node is node 0, as on a ring), edge (beyond an "
            f"end, the end node's own value) or a finite number (the value beyond the ends, e.g. 0.0); got {value!r}."
        )
    users = [s for s, e in zip(states, rhs, strict=True) if e.has(SHIFT)]
    if not users:
        return None
    graph = spec.get("graph")
    if graph == "ring":
        return "wrap"
    on = f"the spec's graph is {graph!r}, not a ring" if graph is not None else "the spec names no graph: ring"
    command_line = where.removesuffix(".spec")  # model.spec -> model.shift_boundary=, as the other inline keys
    raise ConfigError(
        f"{where}.equations.{users[0]} uses shift(...), which reads the nodes in their order, but {on}: say what "
        "shift reads beyond the first and last node. Set shift_boundary: wrap (periodic), edge (the end node's own "
        f"value) or a number (e.g. 0.0) in the spec, or {command_line}.shift_boundary=0.0 on the command line."
    )


def _inputs(value: Any, states: list[str], where: str) -> list[str]:
    """The spec's input names, checked: identifiers, each once, none the name of a state."""
    inputs = _names(value, "inputs", where)
    if len(set(inputs)) != len(inputs):
        raise ConfigError(f"{where}.inputs lists a name twice: {inputs}.")
    for name in inputs:
        _check_name(name, where, "input")
        if name in states:
            raise ConfigError(
                f"{where}.inputs names {name!r}, which is also a state; a name is either a state (with an "
                "equation) or an input (given by the data). Rename one."
            )
    return inputs


def _plain(value: Any) -> Any:
    """A spec value as JSON-able containers (OmegaConf containers and tuples become dicts and lists)."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, Sequence) and not isinstance(value, str):
        return [_plain(v) for v in value]
    return value


def _node_count(nodes: Any, params: dict[str, torch.Tensor], d: int, where: str) -> int | None:
    sizes: dict[str, int] = {}
    if nodes is not None:
        if not isinstance(nodes, int) or isinstance(nodes, bool) or nodes < 1:
            raise ConfigError(f"{where}.nodes must be a positive integer; got {nodes!r}.")
        sizes["nodes"] = nodes
    for name, value in params.items():
        if value.dim() == 1:
            sizes[f"params.{name} (per node)"] = value.numel()
        elif value.dim() == 2:
            if value.shape[0] % d:
                raise ConfigError(
                    f"{where}.params.{name} is {value.shape[0]}×{value.shape[0]}, not a multiple of the "
                    f"{d} states per node: a matrix parameter must be [N·D, N·D]."
                )
            sizes[f"params.{name} (matrix/{d})"] = value.shape[0] // d
    if len(set(sizes.values())) > 1:
        listing = ", ".join(f"{k}: {v}" for k, v in sizes.items())
        raise ConfigError(
            f"{where}: the node counts disagree ({listing}); make every per-node list length N and "
            "every matrix N·D square."
        )
    return next(iter(sizes.values()), None)


def check_nodes(spec: Spec, n_nodes: int, where: str) -> None:
    """Refuse data with another node count than a spec's per-node or matrix parameters fix."""
    if spec.n_nodes is not None and spec.n_nodes != n_nodes:
        raise ConfigError(
            f"{where} is written for {spec.n_nodes} nodes (its per-node/matrix parameters or `nodes:`) "
            f"but the data has {n_nodes}; give parameters for {n_nodes} nodes."
        )


def check_states(spec: Spec, state_names: Sequence[str], where: str) -> None:
    """Refuse data whose per-node state names differ from the spec's (same names, same order)."""
    names, want = list(state_names), list(spec.columns)
    if names != want:
        if sorted(names) == sorted(want):
            why = "the same names in another order; list states in the data's column order"
        else:
            why = f"missing {[s for s in want if s not in names]}, extra {[s for s in names if s not in want]}"
        if spec.outputs:
            what = f"{where} states {list(spec.states)} and outputs {list(spec.outputs)}"
            raise ConfigError(f"{what} do not match the data's columns {names} ({why}).")
        raise ConfigError(f"{where}.states {want} do not match the data's states {names} ({why}).")
