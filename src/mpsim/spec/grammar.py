"""The expression grammar of specs: Python syntax read with `ast` through an allowlist of nodes and rebuilt as sympy
(nothing is evaluated). Names, functions, neighbour terms and `shift` are described in `mpsim.spec`."""

from __future__ import annotations

import ast
import math
from collections.abc import Callable, Sequence
from typing import Any

import sympy
import torch

from mpsim.errors import ConfigError, did_you_mean

SUM_NBR = sympy.Function("sum_nbr")
MEAN_NBR = sympy.Function("mean_nbr")
LIN = sympy.Function("lin")
SHIFT = sympy.Function("shift")  # shift(x, k): x at node i + k in the node order (the boundary: `Spec.shift_boundary`)
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
ORDER_FUNCS = ("lin", "shift")  # functions of the whole node vector, outside neighbour sums
RESERVED = {"t", "deg", "pi", *FUNCS, *NEIGHBOUR_FUNCS, *ORDER_FUNCS}
SHIFT_USAGE = (
    "shift(x, k) is x at node i + k in the node order, x a state, input or per-node parameter and k a whole "
    "number: shift(x, 1), shift(x, -2)"
)
NEIGHBOUR_SUFFIX = "_j"


class Parser:
    """Python-syntax expressions -> sympy, through an allowlist of `ast` nodes (nothing is evaluated)."""

    BINOPS = {
        ast.Add: lambda a, b: a + b,
        ast.Sub: lambda a, b: a - b,
        ast.Mult: lambda a, b: a * b,
        ast.Div: lambda a, b: a / b,
        ast.Pow: lambda a, b: a**b,
    }

    def __init__(
        self, states: list[str], params: dict[str, torch.Tensor], where: str, inputs: Sequence[str] = ()
    ) -> None:
        self.states, self.params, self.where, self.inputs = states, params, where, list(inputs)
        per_node = [p for p, v in params.items() if v.dim() == 1]
        self.own = {n: sympy.Symbol(n) for n in [*states, *self.inputs, *params]}
        self.neighbour = {
            f"{n}{NEIGHBOUR_SUFFIX}": sympy.Symbol(f"{n}{NEIGHBOUR_SUFFIX}") for n in [*states, *self.inputs, *per_node]
        }
        self.known = [
            *states,
            *self.inputs,
            *params,
            *self.neighbour,
            "t",
            "deg",
            "pi",
            *FUNCS,
            *NEIGHBOUR_FUNCS,
            *ORDER_FUNCS,
        ]

    def parse(self, state: str, text: Any, key: str = "equations") -> sympy.Expr:
        """The expression `text` of `<where>.<key>.<state>` (messages name that key)."""
        self.at = f"{self.where}.{key}.{state}"
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
            f"{', '.join(FUNCS)}, sum_nbr, mean_nbr, lin, shift",
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
            raise self.fail(node, f"{n!r}: only states, inputs and per-node parameters have a neighbour's value")
        if n in FUNCS or n in NEIGHBOUR_FUNCS or n in ORDER_FUNCS:
            raise self.fail(node, f"{n!r} is a function: call it, e.g. {n}(...)")
        inputs = f"inputs {self.inputs}, " if self.inputs else ""
        raise self.fail(
            node,
            f"unknown name {n!r}.{did_you_mean(n, self.known)} Known: states {self.states}, {inputs}"
            f"parameters {sorted(self.params)}, t, deg, pi (a value the data give, such as a force, is "
            "declared under inputs:)",
        )

    def call(self, node: ast.Call, in_nbr: bool) -> sympy.Expr:
        if not isinstance(node.func, ast.Name):
            raise self.fail(node, "only plain function names can be called")
        f = node.func.id
        if f == "shift":
            return self.shift(node, in_nbr)
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
            f"unknown function {f!r}.{did_you_mean(f, [*FUNCS, *NEIGHBOUR_FUNCS, *ORDER_FUNCS])} "
            f"Functions: {', '.join([*FUNCS, *NEIGHBOUR_FUNCS, *ORDER_FUNCS])}",
        )

    def shift(self, node: ast.Call, in_nbr: bool) -> sympy.Expr:
        """shift(x, k) -> SHIFT(x, k) (shift(x, 0) is x), x a node's own state, input or per-node parameter."""
        if in_nbr:
            raise self.fail(
                node,
                "shift(...) cannot be used inside a neighbour sum (it reads the node order, not the graph's edges); "
                "take it out of the sum, e.g. shift(x, 1)*sum_nbr(...)",
            )
        if node.keywords or len(node.args) != 2:
            got = len(node.args) + len(node.keywords)
            raise self.fail(node, f"shift(...) takes two arguments, got {got}: {SHIFT_USAGE}")
        what, by = node.args
        k = _whole_number(by)
        if k is None:
            raise self.fail(by, f"shift's step must be a whole number, got {ast.unparse(by)!r}: {SHIFT_USAGE}")
        if not isinstance(what, ast.Name):
            hint = " (write shift(x, 3) for shift(shift(x, 1), 2))" if isinstance(what, ast.Call) else ""
            raise self.fail(
                what,
                f"shift's first argument must be a name, got {ast.unparse(what)!r}{hint}: {SHIFT_USAGE}; shift each "
                "name of an expression, e.g. sin(shift(x, 1))",
            )
        symbol = self.name(what, in_nbr=False)  # unknown names, neighbour names, matrices: its own message
        n = what.id
        per_node = n in self.states or n in self.inputs or (n in self.params and self.params[n].dim() == 1)
        if not per_node:
            kind = "a scalar parameter, the same at every node" if n in self.params else "not a per-node value"
            raise self.fail(what, f"shift({n}, ...): {n!r} is {kind}; {SHIFT_USAGE}")
        return symbol if k == 0 else SHIFT(symbol, sympy.Integer(k))


def _whole_number(node: ast.AST) -> int | None:
    """The integer a literal such as 2, -1 or +3 writes (None for anything else: 1.5, 1.0, a name)."""
    sign = 1
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
        sign, node = (-1 if isinstance(node.op, ast.USub) else 1), node.operand
    if isinstance(node, ast.Constant) and isinstance(node.value, int) and not isinstance(node.value, bool):
        return sign * node.value
    return None
