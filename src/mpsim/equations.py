"""Equations written as text: a spec of states, right-hand sides and parameters, parsed safely into sympy and
compiled to vectorised torch code over batch × nodes × edges.

A spec is plain data (a YAML file or the same keys inline in a config)::

    states: [theta, omega]                 # per node, in the data's column order
    equations:                             # d(state)/dt, one expression per state
      theta: omega
      omega: -(g/l)*sin(theta) - k*sum_nbr(theta - theta_j)
    params: {g: 9.81, l: 1.5, k: 2.0}      # scalar, per-node list (length N), or matrix [N·D, N·D]
    learnable: [g, k]                      # what training fits (default: every parameter)

Expressions use + - * / ** (or ^), numbers, `pi`, the functions sin cos tan exp log sqrt abs sign tanh, `t`
(absolute time), the node's own states and parameters by name, and neighbour terms over the data's graph:
`sum_nbr(e)` / `mean_nbr(e)` evaluate `e` on every edge j → i, where `x_j` is the neighbour's value of state
(or per-node parameter) `x` and a plain `x` the receiving node's own; `deg` is a node's in-degree; `lin(H)` is
this node's and this state's entry of H·vec(X) with X the [N, D] node states flattened node-major.

Nothing in a spec is executed: expressions are read with Python's `ast` parser, every node is checked against
the grammar above and then rebuilt as a sympy expression, which is compiled once into a tree of torch
operations. Subexpressions that recur are evaluated once per call; a sub-term of a neighbour sum that reads
only one end of the edge is evaluated per node and gathered, so `sin(theta_j)` costs one `sin` per node.
"""

from __future__ import annotations

import ast
import keyword
import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import sympy
import torch
import yaml

from mpsim.errors import ConfigError, did_you_mean
from mpsim.graphs.batch import BatchedGraph, segment_sum
from mpsim.safeload import SPEC_BYTES, BoundedLoader, load_yaml, not_a_regular_file

SUM_NBR = sympy.Function("sum_nbr")
MEAN_NBR = sympy.Function("mean_nbr")
LIN = sympy.Function("lin")
NEIGHBOUR_FUNCS = {"sum_nbr": SUM_NBR, "mean_nbr": MEAN_NBR}
FUNCS: dict[str, Any] = {
    "sin": sympy.sin,
    "cos": sympy.cos,
    "tan": sympy.tan,
    "exp": sympy.exp,
    "log": sympy.log,
    "sqrt": sympy.sqrt,
    "abs": sympy.Abs,
    "sign": sympy.sign,
    "tanh": sympy.tanh,
}
TORCH_FUNCS: dict[Any, Callable[[torch.Tensor], torch.Tensor]] = {
    sympy.sin: torch.sin,
    sympy.cos: torch.cos,
    sympy.tan: torch.tan,
    sympy.exp: torch.exp,
    sympy.log: torch.log,
    sympy.Abs: torch.abs,
    sympy.sign: torch.sign,
    sympy.tanh: torch.tanh,
}
T, DEG = sympy.Symbol("t"), sympy.Symbol("deg")
RESERVED = {"t", "deg", "pi", *FUNCS, *NEIGHBOUR_FUNCS, "lin"}
NEIGHBOUR_SUFFIX = "_j"
#: spec keys every spec may have; systems add their own (initial ranges, graph, ...)
MODEL_KEYS = ("states", "equations", "params", "learnable", "kinematic", "nodes", "description")
#: what a simulation also needs (`system=equations`); a model reads the same file and ignores them
SYSTEM_KEYS = ("name", "graph", "graph_params", "edges", "directed", "init", "dt", "horizon", "integrator", "substep")


class _SpecLoader(BoundedLoader):
    """`yaml.SafeLoader` (bounded: `mpsim.safeload`) that also reads `1e-3` and `2E5` as numbers (YAML 1.2 and
    OmegaConf do; PyYAML's YAML 1.1 reads them as text without a dot), so a spec file means what the same keys
    inline in a config mean."""


_SpecLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def load_spec_file(path: str | Path) -> dict[str, Any]:
    """Read a spec from a YAML file (safe loading: plain data only, no tags that build objects), at most
    `SPEC_BYTES` and nested and aliased within the bounds of `mpsim.safeload`.

    Raises:
        ConfigError: the file is missing, not a regular file, unreadable or not a YAML mapping.
        InputLimitError: it is larger, deeper or expands more aliases than mpsim reads.
    """
    path = Path(path)
    why = not_a_regular_file(path)
    if why is not None:
        raise ConfigError(
            f"spec file {path} {why}; give a path to a YAML file (absolute, or relative to the directory you "
            "started mpsim from)."
        )
    fix = "Give a spec of plain states, equations and params (limits: docs/equations.md)"
    try:
        data = load_yaml(path, SPEC_BYTES, f"spec file {path}", fix, loader=_SpecLoader)
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ConfigError(f"cannot read spec file {path}: {first}. Fix the YAML (states, equations, params).") from None
    if not isinstance(data, dict):
        raise ConfigError(
            f"spec file {path} holds a {type(data).__name__}, not a mapping of states, equations, params."
        )
    return data


# ---- the spec ------------------------------------------------------------------------------------------------
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
    """

    states: tuple[str, ...]
    rhs: tuple[sympy.Expr, ...]
    params: dict[str, torch.Tensor]
    learnable: tuple[str, ...]
    kinematic: tuple[str, ...]
    n_nodes: int | None
    raw: dict[str, Any] = field(repr=False)
    where: str = "model.spec"

    @property
    def state_dim(self) -> int:
        return len(self.states)

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
            "(mpsim.equations.load_spec_file)."
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
    raw_params = spec.get("params") or {}
    if not isinstance(raw_params, Mapping):
        raise ConfigError(f"{where}.params must be a mapping name: value; got {type(raw_params).__name__}.")
    params: dict[str, torch.Tensor] = {}
    for name, value in raw_params.items():
        _check_name(str(name), where, "parameter")
        if name in states:
            raise ConfigError(f"{where}.params.{name} has the name of a state; rename the parameter.")
        params[str(name)] = _param_value(str(name), value, where)
    n_nodes = _node_count(spec.get("nodes"), params, len(states), where)

    equations = spec.get("equations")
    if not isinstance(equations, Mapping):
        raise ConfigError(f"{where}.equations is missing: give one expression per state, e.g. {{{states[0]}: ...}}.")
    for key in equations:
        if key not in states:
            raise ConfigError(
                f"{where}.equations.{key}: {key!r} is not a state.{did_you_mean(str(key), states)} States: {states}."
            )
    missing = [s for s in states if s not in equations]
    if missing:
        raise ConfigError(f"{where}.equations has no equation for {missing}; give d/dt of every state.")
    parser = _Parser(states, params, where)
    rhs = tuple(parser.parse(s, equations[s]) for s in states)

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
    return Spec(tuple(states), rhs, params, tuple(learnable), tuple(kinematic), n_nodes, plain, where)


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


class _Parser:
    """Python-syntax expressions -> sympy, through an allowlist of `ast` nodes (nothing is evaluated)."""

    BINOPS = {
        ast.Add: lambda a, b: a + b,
        ast.Sub: lambda a, b: a - b,
        ast.Mult: lambda a, b: a * b,
        ast.Div: lambda a, b: a / b,
        ast.Pow: lambda a, b: a**b,
    }

    def __init__(self, states: list[str], params: dict[str, torch.Tensor], where: str) -> None:
        self.states, self.params, self.where = states, params, where
        per_node = [p for p, v in params.items() if v.dim() == 1]
        self.own = {n: sympy.Symbol(n) for n in [*states, *params]}
        self.neighbour = {
            f"{n}{NEIGHBOUR_SUFFIX}": sympy.Symbol(f"{n}{NEIGHBOUR_SUFFIX}") for n in [*states, *per_node]
        }
        self.known = [*states, *params, *self.neighbour, "t", "deg", "pi", *FUNCS, *NEIGHBOUR_FUNCS, "lin"]

    def parse(self, state: str, text: Any) -> sympy.Expr:
        self.at = f"{self.where}.equations.{state}"
        if isinstance(text, int | float) and not isinstance(text, bool):
            return sympy.Float(text) if isinstance(text, float) else sympy.Integer(text)
        if not isinstance(text, str) or not text.strip():
            raise ConfigError(f"{self.at}: expected an expression (text); got {text!r}.")
        try:
            # ^ means power (as in papers); Python's ^ binds looser than +, so rewrite it before parsing
            tree = ast.parse(text.strip().replace("^", "**"), mode="eval")
        except SyntaxError as err:
            raise ConfigError(f"{self.at}: cannot parse {text!r}: {err.msg} at column {err.offset}.") from None
        return self.visit(tree.body, in_nbr=False)

    def fail(self, node: ast.AST, why: str) -> ConfigError:
        return ConfigError(f"{self.at}: {why} (at column {getattr(node, 'col_offset', 0) + 1}).")

    def visit(self, node: ast.AST, in_nbr: bool) -> sympy.Expr:
        if isinstance(node, ast.Constant) and isinstance(node.value, int | float) and not isinstance(node.value, bool):
            return sympy.Integer(node.value) if isinstance(node.value, int) else sympy.Float(node.value)
        if isinstance(node, ast.BinOp) and type(node.op) in self.BINOPS:
            left, right = self.visit(node.left, in_nbr), self.visit(node.right, in_nbr)
            if isinstance(node.op, ast.Pow):
                self.check_power(node, left, right)
            return self.BINOPS[type(node.op)](left, right)
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
            inner = self.visit(node.operand, in_nbr)
            return -inner if isinstance(node.op, ast.USub) else inner
        if isinstance(node, ast.Name):
            return self.name(node, in_nbr)
        if isinstance(node, ast.Call):
            return self.call(node, in_nbr)
        what = type(node).__name__
        raise self.fail(
            node,
            f"{what} is not allowed; use numbers, names, + - * / ** and the functions "
            f"{', '.join(FUNCS)}, sum_nbr, mean_nbr, lin",
        )

    def check_power(self, node: ast.BinOp, base: sympy.Expr, exponent: sympy.Expr) -> None:
        """A power of two numbers is computed exactly when it is read (9**9**9**9 would take forever and all
        memory): refuse one whose value passes 1e300 (a float64's range) in size."""
        if not (base.is_Number and exponent.is_Number) or base in (0, 1, -1):
            return
        size = float(exponent) * math.log10(abs(float(base)))  # log10 of |value|
        if abs(size) > 300:
            raise self.fail(
                node,
                f"the constant {base}**{exponent} is about 10^{size:.3g}, beyond float64; write a number within range",
            )

    def name(self, node: ast.Name, in_nbr: bool) -> sympy.Expr:
        n = node.id
        if n == "pi":
            return sympy.pi
        if n == "t":
            return T
        if n == "deg":
            return DEG
        if n in self.own:
            if n in self.params and self.params[n].dim() == 2:
                raise self.fail(node, f"matrix parameter {n!r} can only be used as lin({n})")
            return self.own[n]
        if n in self.neighbour:
            if not in_nbr:
                raise self.fail(
                    node, f"{n!r} (a neighbour's value) is only defined inside sum_nbr(...) or mean_nbr(...)"
                )
            return self.neighbour[n]
        if n.endswith(NEIGHBOUR_SUFFIX) and n[: -len(NEIGHBOUR_SUFFIX)] in self.params:
            raise self.fail(node, f"{n!r}: only states and per-node parameters have a neighbour's value")
        if n in FUNCS or n in NEIGHBOUR_FUNCS or n == "lin":
            raise self.fail(node, f"{n!r} is a function: call it, e.g. {n}(...)")
        raise self.fail(
            node,
            f"unknown name {n!r}.{did_you_mean(n, self.known)} Known: states {self.states}, "
            f"parameters {sorted(self.params)}, t, deg, pi",
        )

    def call(self, node: ast.Call, in_nbr: bool) -> sympy.Expr:
        if not isinstance(node.func, ast.Name):
            raise self.fail(node, "only plain function names can be called")
        f = node.func.id
        if node.keywords or len(node.args) != 1:
            raise self.fail(node, f"{f}(...) takes exactly one argument")
        arg = node.args[0]
        if f in FUNCS:
            return FUNCS[f](self.visit(arg, in_nbr))
        if f in NEIGHBOUR_FUNCS:
            if in_nbr:
                raise self.fail(node, f"{f}(...) cannot be nested inside another neighbour sum")
            return NEIGHBOUR_FUNCS[f](self.visit(arg, in_nbr=True))
        if f == "lin":
            if in_nbr:
                raise self.fail(node, "lin(...) cannot be used inside a neighbour sum")
            if not (isinstance(arg, ast.Name) and arg.id in self.params and self.params[arg.id].dim() == 2):
                matrices = [p for p, v in self.params.items() if v.dim() == 2]
                raise self.fail(node, f"lin(...) takes the name of a matrix parameter (have: {matrices or 'none'})")
            return LIN(sympy.Symbol(arg.id))
        raise self.fail(
            node,
            f"unknown function {f!r}.{did_you_mean(f, [*FUNCS, *NEIGHBOUR_FUNCS, 'lin'])} "
            f"Functions: {', '.join([*FUNCS, *NEIGHBOUR_FUNCS, 'lin'])}",
        )


# ---- compilation -----------------------------------------------------------------------------------------------
Value = Any  # torch.Tensor ([], [N], [B, N] or [E']) or a Python float


class _Env:
    """What one evaluation reads: time, states, parameter values, graph, and a per-call cache."""

    __slots__ = ("t", "x", "cols", "p", "graph", "cache", "b", "n")

    def __init__(self, t, x, p, graph) -> None:  # x: [B, N, D]
        self.cache: dict = {}
        self.t, self.x, self.p, self.graph = t, x, p, graph
        self.cols = x.unbind(-1)  # D views [B, N]: one operation for every state's column
        self.b, self.n = x.shape[0], x.shape[1]


def _full(v: Value, env: _Env) -> torch.Tensor:
    """[B·N] a node-level value broadcast over the batch and flattened."""
    if not torch.is_tensor(v):
        v = env.x.new_tensor(v)
    return v.expand(env.b, env.n).reshape(-1)


class EquationField:
    """The compiled right-hand side of a spec: `field(t, x, params, graph) -> dx/dt [B, N, D]`.

    Args:
        spec: the parsed spec.
    """

    def __init__(self, spec: Spec) -> None:
        self.spec = spec
        self.index = {s: i for i, s in enumerate(spec.states)}
        self.node_memo: dict[Any, tuple[int, Callable]] = {}
        self.edge_memo: dict[Any, Callable] = {}
        self.counts: dict[Any, int] = {}
        for expr in spec.rhs:
            for sub in sympy.preorder_traversal(expr):
                self.counts[sub] = self.counts.get(sub, 0) + 1
        self.uses_graph = any(e.has(SUM_NBR) or e.has(MEAN_NBR) or e.has(DEG) for e in spec.rhs)
        self.matrices = sorted({str(a.args[0]) for e in spec.rhs for a in e.atoms(LIN)})
        self.columns = []
        for i, e in enumerate(spec.rhs):
            try:
                self.columns.append(self.node(e, i)[1])
            except ConfigError as err:
                raise ConfigError(f"{spec.where}.equations.{spec.states[i]}: {err}") from None

    def __call__(
        self,
        t: torch.Tensor,  # [] time (or [M, 1] one per state)
        x: torch.Tensor,  # [B, N, D] states
        params: Mapping[str, torch.Tensor],  # name -> [] / [N] / [N·D, N·D] value
        graph: BatchedGraph | None = None,  # the B graphs flattened (needed for neighbour terms and deg)
    ) -> torch.Tensor:
        """[B, N, D] dx/dt."""
        if self.uses_graph and graph is None:
            raise ConfigError("these equations have neighbour terms (sum_nbr, mean_nbr, deg) but no graph was given.")
        env = _Env(t, x, params, graph)
        b, n = x.shape[0], x.shape[1]
        out = []
        for f in self.columns:
            v = f(env)
            out.append(v if torch.is_tensor(v) and v.shape == (b, n) else torch.broadcast_to(_as_tensor(v, x), (b, n)))
        return torch.stack(out, dim=-1)

    # node-level: value per node ([], [N] or [B, N]); rank orders products (scalars multiply first)
    def node(self, expr: sympy.Expr, state: int) -> tuple[int, Callable[[_Env], Value]]:
        key = (expr, state if expr.has(LIN) else None)
        if key not in self.node_memo:
            rank, fn = self._node(expr, state)
            if self.counts.get(expr, 0) > 1 and rank >= 2:
                fn = _cached(fn, len(self.node_memo))
            self.node_memo[key] = (rank, fn)
        return self.node_memo[key]

    def _node(self, expr: sympy.Expr, state: int) -> tuple[int, Callable[[_Env], Value]]:
        if not expr.free_symbols and not expr.has(SUM_NBR, MEAN_NBR, LIN):
            try:
                c = float(expr)
            except (TypeError, OverflowError, ValueError):
                c = math.nan
            if not math.isfinite(c):
                raise ConfigError(
                    f"{str(expr)[:80]} is not a finite real number (float64); check the spec's constants."
                ) from None
            return 0, lambda env: c
        if isinstance(expr, sympy.Symbol):
            name = expr.name
            if name in self.index:
                i = self.index[name]
                return 3, lambda env: env.cols[i]
            if name == "t":
                return 3, lambda env: env.t
            if name == "deg":
                return 3, _degree
            rank = 1 if self.spec.params[name].dim() == 0 else 2
            return rank, lambda env: env.p[name]
        if expr.is_Add:
            return self._add([self.node(a, state) for a in expr.args])
        if expr.is_Mul:
            return self._mul([self.node(a, state) for a in expr.args], expr)
        if expr.is_Pow:
            return self._pow(self.node(expr.base, state), expr.exp, lambda e: self.node(e, state))
        if expr.func in (SUM_NBR, MEAN_NBR):
            return 3, self._aggregate(self.edge(expr.args[0]), mean=expr.func == MEAN_NBR)
        if expr.func == LIN:
            name, key = str(expr.args[0]), ("lin", str(expr.args[0]))

            def lin(env: _Env) -> torch.Tensor:
                prod = env.cache.get(key)
                if prod is None:
                    b, n, d = env.x.shape
                    prod = env.cache[key] = (env.x.reshape(b, n * d) @ env.p[name].T).view(b, n, d)
                return prod[..., state]

            return 3, lin
        if expr.func in TORCH_FUNCS:
            rank, inner = self.node(expr.args[0], state)
            return rank, _apply(TORCH_FUNCS[expr.func], inner)
        raise ConfigError(f"cannot compile {expr} (an expression sympy produced from the spec); please report it.")

    # edge-level: value per edge [E'] (or node-independent); terms that read one end are computed per node
    def edge(self, expr: sympy.Expr) -> Callable[[_Env], Value]:
        if expr not in self.edge_memo:
            self.edge_memo[expr] = self._edge(expr)
        return self.edge_memo[expr]

    def _edge(self, expr: sympy.Expr) -> Callable[[_Env], Value]:
        names = {s.name for s in expr.free_symbols}
        nbr = {n for n in names if n.endswith(NEIGHBOUR_SUFFIX)}
        own = {
            n
            for n in names
            if n not in nbr
            and (n in self.index or n in ("t", "deg") or (n in self.spec.params and self.spec.params[n].dim() == 1))
        }
        if not nbr:
            rank, fn = self.node(expr, -1)
            if rank <= 1:
                return fn
            return lambda env: _full(fn(env), env).index_select(0, env.graph.dst)
        if not own:
            swap = {sympy.Symbol(n): sympy.Symbol(n[: -len(NEIGHBOUR_SUFFIX)]) for n in nbr}
            _, fn = self.node(expr.xreplace(swap), -1)
            return lambda env: _full(fn(env), env).index_select(0, env.graph.src)
        if expr.is_Add:
            return self._add([(3, self.edge(a)) for a in expr.args])[1]
        if expr.is_Mul:
            return self._mul([(3, self.edge(a)) for a in expr.args], expr)[1]
        if expr.is_Pow:
            return self._pow((3, self.edge(expr.base)), expr.exp, lambda e: (3, self.edge(e)))[1]
        if expr.func in TORCH_FUNCS:
            return _apply(TORCH_FUNCS[expr.func], self.edge(expr.args[0]))
        raise ConfigError(f"cannot compile {expr} inside a neighbour sum; please report it.")

    # ---- operations ------------------------------------------------------------------------------------------
    @staticmethod
    def _aggregate(edge_fn: Callable[[_Env], Value], mean: bool) -> Callable[[_Env], torch.Tensor]:
        def aggregate(env: _Env) -> torch.Tensor:
            g = env.graph
            v = edge_fn(env)
            if not torch.is_tensor(v) or v.dim() == 0 or v.shape[0] != g.dst.shape[0]:
                v = _as_tensor(v, env.x).expand(g.dst.shape[0])
            out = segment_sum(v.to(env.x.dtype), g.dst, env.b * env.n)
            if mean:
                out = out * g.inv_degree[:, 0].to(out.dtype)
            return out.view(env.b, env.n)

        return aggregate

    @staticmethod
    def _add(terms: list[tuple[int, Callable]]) -> tuple[int, Callable]:
        # a − b arrives as a + (−1)·b: subtract instead of negating
        fns = [fn for _, fn in terms if getattr(fn, "negated", None) is None]
        negs = [neg for _, fn in terms if (neg := getattr(fn, "negated", None)) is not None]
        rank = max(r for r, _ in terms)

        def add(env: _Env) -> Value:
            acc = fns[0](env) if fns else -negs[0](env)
            for f in fns[1:]:
                acc = acc + f(env)
            for f in negs[0 if fns else 1 :]:
                acc = acc - f(env)
            return acc

        return rank, add

    @staticmethod
    def _mul(factors: list[tuple[int, Callable]], expr: sympy.Expr) -> tuple[int, Callable]:
        # −1 as a factor becomes a negation (so that a sum subtracts); 1/b as a factor becomes a division;
        # factors are applied in rank order, so scalar parameters combine before touching per-node tensors
        negative = False
        ops: list[tuple[int, bool, Callable]] = []  # (rank, divide, fn)
        for (rank, fn), arg in zip(factors, expr.args, strict=True):
            if arg.is_Number and float(arg) == -1.0 and not negative:
                negative = True
                continue
            recip = getattr(fn, "reciprocal_of", None)
            ops.append((rank, True, recip) if recip is not None else (rank, False, fn))
        ops.sort(key=lambda r: r[0])
        if ops and ops[0][1]:  # start from a multiplied factor where there is one
            first = next((i for i, o in enumerate(ops) if not o[1]), None)
            if first is not None:
                ops.insert(0, ops.pop(first))
        rank = max(r for r, _ in factors)
        steps = [(divide, fn) for _, divide, fn in ops]

        def positive(env: _Env) -> Value:
            divide, fn = steps[0]
            acc = 1.0 / _as_tensor(fn(env), env.x) if divide else fn(env)
            for divide, fn in steps[1:]:
                acc = acc / fn(env) if divide else acc * fn(env)
            return acc

        if not steps:
            return 0, lambda env: -1.0
        if negative:

            def mul(env: _Env) -> Value:
                return -positive(env)

            mul.negated = positive  # type: ignore[attr-defined]
            return rank, mul
        return rank, positive

    @staticmethod
    def _pow(base: tuple[int, Callable], exponent: sympy.Expr, compile_exp: Callable) -> tuple[int, Callable]:
        rank, b = base
        if exponent.is_Number:
            e = float(exponent)
            if e == -1.0:
                fn = _apply(lambda v: 1.0 / v, b)
                fn.reciprocal_of = b  # type: ignore[attr-defined]
                return rank, fn
            if e == 2.0:
                return rank, _apply(lambda v: v * v, b)
            if e == 0.5:
                return rank, _apply(torch.sqrt, b)
            if e < 0:
                pos = _apply(lambda v: v ** (-e), b)
                fn = _apply(lambda v: 1.0 / v, pos)
                fn.reciprocal_of = pos  # type: ignore[attr-defined]
                return rank, fn
            return rank, _apply(lambda v: v**e, b)
        erank, ef = compile_exp(exponent)

        def power(env: _Env) -> Value:
            return _as_tensor(b(env), env.x) ** ef(env)

        return max(rank, erank), power


def _as_tensor(v: Value, like: torch.Tensor) -> torch.Tensor:
    return v if torch.is_tensor(v) else like.new_tensor(v)


def _apply(op: Callable[[Any], Any], inner: Callable[[_Env], Value]) -> Callable[[_Env], Value]:
    def apply(env: _Env) -> Value:
        v = inner(env)
        if not torch.is_tensor(v):
            v = env.x.new_tensor(v)
        return op(v)

    return apply


def _cached(fn: Callable[[_Env], Value], key: Any) -> Callable[[_Env], Value]:
    def cached(env: _Env) -> Value:
        v = env.cache.get(key)
        if v is None:
            v = env.cache[key] = fn(env)
        return v

    for attr in ("negated", "reciprocal_of"):
        if hasattr(fn, attr):
            setattr(cached, attr, getattr(fn, attr))
    return cached


def _degree(env: _Env) -> torch.Tensor:
    g = env.graph
    v = env.cache.get("deg")
    if v is None:
        ones = env.x.new_ones(g.dst.shape[0])
        v = env.cache["deg"] = env.x.new_zeros(env.b * env.n).index_add_(0, g.dst, ones).view(env.b, env.n)
    return v


def check_nodes(spec: Spec, n_nodes: int, where: str) -> None:
    """Refuse data with another node count than a spec's per-node or matrix parameters fix."""
    if spec.n_nodes is not None and spec.n_nodes != n_nodes:
        raise ConfigError(
            f"{where} is written for {spec.n_nodes} nodes (its per-node/matrix parameters or `nodes:`) "
            f"but the data has {n_nodes}; give parameters for {n_nodes} nodes."
        )


def check_states(spec: Spec, state_names: Sequence[str], where: str) -> None:
    """Refuse data whose per-node state names differ from the spec's (same names, same order)."""
    names = list(state_names)
    if names != list(spec.states):
        if sorted(names) == sorted(spec.states):
            why = "the same names in another order; list states in the data's column order"
        else:
            why = f"missing {[s for s in spec.states if s not in names]}, extra {[s for s in names if s not in spec.states]}"
        raise ConfigError(f"{where}.states {list(spec.states)} do not match the data's states {names} ({why}).")
