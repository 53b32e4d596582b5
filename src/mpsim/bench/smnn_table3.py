"""Paper Table 3 (S-MNN as a standalone ODE solver): six linear ODEs of ODEBench, relative MSE per derivative order.

Setup (spec `shared/reference/smnn_reference.md` §4.1): 1000 steps of h = 0.01 from t = 0, float64, O = 3 orders
(u, u', u''), only x₀(0) as initial value, no central rows, unit weights; the metric is, for the first variable
and each order k, relMSE_k = mean_t (û_k − x₀⁽ᵏ⁾)² / Var_t(x₀⁽ᵏ⁾) against the closed-form solution's
derivatives.
`mpsim bench bench=smnn_table3` prints it next to the published values, for every solver, with solve times.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import torch

from mpsim.bench.common import Suite, timeit
from mpsim.metrics import relative_mse
from mpsim.solvers.mnn_dense import dense_solve
from mpsim.solvers.smnn import smnn_solve

F64 = torch.float64
ORDERS = ("u", "u'", "u''")


class LinearODE(NamedTuple):
    """One Table 3 system: EQ rows Σ c·[u, u', u''] = r, the first initial value set, the closed form of x₀."""

    title: str
    coefficients: list  # [1, E, D, 3]
    rhs: list  # [1, E]
    init: list  # [D] values at t = 0
    closed_form: Callable[[torch.Tensor, list], torch.Tensor]  # (t [T], init) -> x₀(t) [T]
    published: tuple[float, float, float]  # paper's S-MNN relative MSE for u, u', u''


def table3_systems() -> dict[str, LinearODE]:
    """The six ODEs of paper Table 3 by their column letter (constants and initial values of spec §4.1)."""
    out = {}
    c0, c1, c2 = 0.7, 1.2, 2.31
    out["R"] = LinearODE(
        "RC circuit",
        [[[[1 / c1, c2, 0]]]],
        [[c0]],
        [10.0],
        lambda t, i: c0 * c1 + (i[0] - c0 * c1) * torch.exp(-t / (c1 * c2)),
        (4.8e-12, 4.8e-12, 2.2e-7),
    )
    p0 = 0.23
    out["P"] = LinearODE(
        "population growth",
        [[[[p0, -1, 0]]]],
        [[0.0]],
        [4.78],
        lambda t, i: i[0] * torch.exp(p0 * t),
        (9.4e-12, 9.4e-12, 9.6e-8),
    )
    l0, l1 = 0.32, 0.28
    out["L"] = LinearODE(
        "language death",
        [[[[l0 + l1, 1, 0]]]],
        [[l0]],
        [0.14],
        lambda t, i: l0 / (l0 + l1) - (l0 / (l0 + l1) - i[0]) * torch.exp(-(l0 + l1) * t),
        (2.6e-11, 2.6e-11, 7.1e-7),
    )
    h0, w0 = 2.1, math.sqrt(2.1)
    out["H"] = LinearODE(
        "harmonic oscillator",
        [[[[0, 1, 0], [-1, 0, 0]], [[h0, 0, 0], [0, 1, 0]]]],
        [[0.0, 0.0]],
        [0.4, -0.03],
        lambda t, i: i[0] * torch.cos(w0 * t) + i[1] / w0 * torch.sin(w0 * t),
        (9.5e-8, 7.7e-8, 5.1e-7),
    )
    d0, d1 = 4.5, 0.43
    w = math.sqrt(d0 - d1**2 / 4)
    out["D"] = LinearODE(
        "damped oscillator",
        [[[[0, 1, 0], [-1, 0, 0]], [[d0, 0, 0], [d1, 1, 0]]]],
        [[0.0, 0.0]],
        [0.12, 0.043],
        lambda t, i: torch.exp(-d1 * t / 2) * (i[0] * torch.cos(w * t) + (d1 * i[0] / 2 + i[1]) / w * torch.sin(w * t)),
        (2.1e-7, 2.3e-7, 4.0e-7),
    )
    r3 = math.sqrt(0.75)
    out["T"] = LinearODE(
        "third order",
        [[[[0, 1, 0], [-1, 0, 0], [0, 0, 0]], [[0, 0, 0], [0, 1, 0], [-1, 0, 0]], [[0, 0, 0], [1, 0, 0], [1, 1, 0]]]],
        [[0.0, 0.0, 0.0]],
        [0.0, -1.0, 1.0],
        lambda t, i: (
            i[0]
            + i[1]
            + i[2]
            + torch.exp(-t / 2)
            * (-(i[1] + i[2]) * torch.cos(r3 * t) + (i[1] - i[2]) / math.sqrt(3) * torch.sin(r3 * t))
        ),
        (1.0e-9, 6.8e-10, 4.3e-9),
    )
    return out


def solver_inputs(ode: LinearODE) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(coefficients [1, E, D, 3], rhs [1, E], init [1, D, 1]) for `smnn_solve` (step dim first = broadcast)."""
    init = torch.tensor(ode.init, dtype=F64)[None, :, None]  # [S=1, D, I=1]: only x(0)
    return torch.tensor(ode.coefficients, dtype=F64), torch.tensor(ode.rhs, dtype=F64), init


def truth(ode: LinearODE, t: torch.Tensor) -> torch.Tensor:  # t: [T] times
    """[T, 3] x₀ and its first two derivatives from the closed form (autograd of the formula)."""
    t = t.clone().requires_grad_(True)
    x = ode.closed_form(t, ode.init)
    d1 = torch.autograd.grad(x.sum(), t, create_graph=True)[0]
    d2 = torch.autograd.grad(d1.sum(), t)[0]
    return torch.stack([x.detach(), d1.detach(), d2], -1)


def solve(method: str, ode: LinearODE, n_steps: int, h: float) -> torch.Tensor:
    """[T, D, 3] the solution of one solver: banded, cyclic (linear time) or dense (same system, dense)."""
    coef, rhs, init = solver_inputs(ode)
    if method == "dense":
        return dense_solve(coef, rhs, init, h, n_steps=n_steps)
    return smnn_solve(coef, rhs, init, torch.tensor([h], dtype=F64), n_steps=n_steps, method=method)


class Table3Bench(Suite):
    """Args:
    methods: solvers to run (banded, cyclic, dense).
    n_steps: T (paper: 1000).
    step: h (paper: 0.01).
    repeats: timing repeats per solve.
    """

    name = "smnn_table3"

    def __init__(
        self,
        methods: Sequence[str] = ("banded", "cyclic", "dense"),
        n_steps: int = 1000,
        step: float = 0.01,
        repeats: int = 5,
    ) -> None:
        bad = [m for m in methods if m not in ("banded", "cyclic", "dense")]
        if bad:
            raise ValueError(f"bench.methods must be among banded, cyclic, dense; got {bad}.")
        self.methods, self.n_steps, self.step, self.repeats = list(methods), int(n_steps), float(step), int(repeats)

    def run(self) -> list[dict[str, Any]]:
        rows = []
        t = torch.arange(self.n_steps, dtype=F64) * self.step
        for key, ode in table3_systems().items():
            exact = truth(ode, t)
            for method in self.methods:
                u = solve(method, ode, self.n_steps, self.step)
                stats = timeit(functools.partial(solve, method, ode, self.n_steps, self.step), repeats=self.repeats)
                err = relative_mse(u, exact)
                for k, order in enumerate(ORDERS):
                    rows.append(
                        {
                            "ode": key,
                            "title": ode.title,
                            "method": method,
                            "order": order,
                            "rel_mse": float(err[k]),
                            "published": ode.published[k],
                            "ratio": float(err[k]) / ode.published[k],
                            "solve_ms": 1e3 * stats["median_s"],
                        }
                    )
        return rows

    def summarise(self, rows: list[dict[str, Any]]) -> list[str]:
        odes = list(dict.fromkeys(r["ode"] for r in rows))
        lines = [
            f"Relative MSE of x₀ and its derivatives, {self.n_steps} steps of {self.step:g} (paper Table 3 "
            "layout; published S-MNN values in brackets).",
            "",
            "| order | " + " | ".join(odes) + " |",
            "|---|" + "---|" * len(odes),
        ]
        for method in self.methods:
            for order in ORDERS:
                cells = [
                    next(
                        f"{r['rel_mse']:.1e} ({r['published']:.1e})"
                        for r in rows
                        if (r["ode"], r["method"], r["order"]) == (o, method, order)
                    )
                    for o in odes
                ]
                lines.append(f"| {order}, {method} | " + " | ".join(cells) + " |")
        ratios = [r["ratio"] for r in rows]
        lines += [
            "",
            f"- measured / published: {min(ratios):.2f} … {max(ratios):.2f} over all {len(ratios)} entries "
            "(target: within a factor 3)",
        ]
        for method in self.methods:
            ms = sorted({r["ode"]: r["solve_ms"] for r in rows if r["method"] == method}.values())
            lines.append(
                f"- {method}: {ms[0]:.1f} … {ms[-1]:.1f} ms per solve (paper, S-MNN on an AMD EPYC 7513: 22–26 ms)"
            )
        return lines
