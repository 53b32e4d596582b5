"""A parsed spec compiled once into a tree of vectorised torch operations over batch × nodes × edges
(`EquationField`): recurring subexpressions are evaluated once per call, a neighbour sum's sub-terms that read
one end of the edge only are evaluated per node and gathered, and `shift(x, k)` gathers x along the node axis."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

import sympy
import torch

from mpsim.errors import ConfigError
from mpsim.graphs.batch import BatchedGraph, segment_sum
from mpsim.spec.grammar import DEG, LIN, MEAN_NBR, NEIGHBOUR_SUFFIX, SHIFT, SUM_NBR, TORCH_FUNCS
from mpsim.spec.parse import Spec

Value = Any  # torch.Tensor ([], [N], [B, N] or [E']) or a Python float


class _Env:
    """What one evaluation reads: time, states, inputs, parameter values, graph, and a per-call cache."""

    __slots__ = ("t", "x", "cols", "ucols", "p", "graph", "cache", "b", "n")

    def __init__(self, t, x, u, p, graph) -> None:  # x: [B, N, D], u: [B, N, C] or None
        self.cache: dict = {}
        self.t, self.x, self.p, self.graph = t, x, p, graph
        self.cols = x.unbind(-1)  # D views [B, N]: one operation for every state's column
        self.ucols = () if u is None else u.to(x).unbind(-1)  # C views [B, N]
        self.b, self.n = x.shape[0], x.shape[1]


def _full(v: Value, env: _Env) -> torch.Tensor:
    """[B·N] a node-level value broadcast over the batch and flattened."""
    if not torch.is_tensor(v):
        v = env.x.new_tensor(v)
    return v.expand(env.b, env.n).reshape(-1)


class EquationField:
    """The compiled right-hand side of a spec: `field(t, x, params, graph, u) -> dx/dt [B, N, D]`.

    Args:
        spec: the parsed spec.
    """

    def __init__(self, spec: Spec, outputs: bool = False) -> None:
        """`outputs`: compile the spec's `outputs` (what the sensors read) instead of its equations."""
        self.spec = spec
        exprs, names, key = (
            (spec.output_exprs, spec.outputs, "outputs") if outputs else (spec.rhs, spec.states, "equations")
        )
        self.index = {s: i for i, s in enumerate(spec.states)}
        self.input_index = {s: i for i, s in enumerate(spec.inputs)}
        self.node_memo: dict[Any, tuple[int, Callable]] = {}
        self.edge_memo: dict[Any, Callable] = {}
        self.counts: dict[Any, int] = {}
        for expr in exprs:
            for sub in sympy.preorder_traversal(expr):
                self.counts[sub] = self.counts.get(sub, 0) + 1
        self.uses_graph = any(e.has(SUM_NBR) or e.has(MEAN_NBR) or e.has(DEG) for e in exprs)
        self.matrices = sorted({str(a.args[0]) for e in exprs for a in e.atoms(LIN)})
        self.columns = []
        for i, e in enumerate(exprs):
            try:
                self.columns.append(self.node(e, i)[1])
            except ConfigError as err:
                raise ConfigError(f"{spec.where}.{key}.{names[i]}: {err}") from None

    def __call__(
        self,
        t: torch.Tensor,  # [] time (or [M, 1] one per state)
        x: torch.Tensor,  # [B, N, D] states
        params: Mapping[str, torch.Tensor],  # name -> [] / [N] / [N·D, N·D] value
        graph: BatchedGraph | None = None,  # the B graphs flattened (needed for neighbour terms and deg)
        u: torch.Tensor | None = None,  # [B, N, C] the spec's inputs at time t (None: the spec has none)
    ) -> torch.Tensor:
        """[B, N, D] dx/dt (or [B, N, P] the outputs, for a field of a spec's outputs)."""
        if self.uses_graph and graph is None:
            raise ConfigError("these equations have neighbour terms (sum_nbr, mean_nbr, deg) but no graph was given.")
        c = len(self.spec.inputs)
        if c and (u is None or u.shape != (*x.shape[:2], c)):
            got = "none" if u is None else f"shape {list(u.shape)}"
            raise ConfigError(
                f"{self.spec.where} reads the inputs {list(self.spec.inputs)}: their values [B, N, C] = "
                f"{[*x.shape[:2], c]} at time t are needed; got {got}."
            )
        env = _Env(t, x, u if c else None, params, graph)
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
            if name in self.input_index:
                k = self.input_index[name]
                return 3, lambda env: env.ucols[k]
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
        if expr.func == SHIFT:
            return 3, self._shift(self.node(expr.args[0], state)[1], int(expr.args[1]))
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
            and (
                n in self.index
                or n in self.input_index
                or n in ("t", "deg")
                or (n in self.spec.params and self.spec.params[n].dim() == 1)
            )
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
    def _shift(self, inner: Callable[[_Env], Value], k: int) -> Callable[[_Env], Value]:
        """shift(x, k): x [B, N] (or [N], a per-node parameter) gathered at node i + k, beyond the ends as
        `spec.shift_boundary` says (wrap: mod N; edge: the end node's value; a number: that value)."""
        boundary = self.spec.shift_boundary
        fill = boundary if isinstance(boundary, float) else 0.0  # read only where `inside` is given (a number)

        def shift(env: _Env) -> torch.Tensor:
            v = _as_tensor(inner(env), env.x)
            index, inside = _shift_index(env, k, boundary)
            out = v.index_select(-1, index)
            if inside is None:
                return out
            return torch.where(inside, out, out.new_full((), fill))

        return shift

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


def _shift_index(env: _Env, k: int, boundary: str | float | None) -> tuple[torch.Tensor, torch.Tensor | None]:
    """([N] the node each node reads, [N] bool whether it lies inside 0..N−1 (None: every one does)) for a step k."""
    key = ("shift", k)
    hit = env.cache.get(key)
    if hit is None:
        n = env.n
        if boundary is None:  # parse_spec refuses shift without a boundary; a Spec built otherwise lands here
            raise ConfigError("shift(...) needs the spec's shift_boundary (wrap, edge or a number).")
        nodes = torch.arange(n, device=env.x.device)
        if boundary == "wrap":
            hit = ((nodes + k % n) % n, None)
        else:
            target = nodes + max(-n, min(n, k))  # a step beyond ±N reads what ±N reads (no integer overflow)
            inside = None if boundary == "edge" else (target >= 0) & (target < n)
            hit = (target.clamp(0, n - 1), inside)
        env.cache[key] = hit
    return hit


def _degree(env: _Env) -> torch.Tensor:
    g = env.graph
    v = env.cache.get("deg")
    if v is None:
        ones = env.x.new_ones(g.dst.shape[0])
        v = env.cache["deg"] = env.x.new_zeros(env.b * env.n).index_add_(0, g.dst, ones).view(env.b, env.n)
    return v
