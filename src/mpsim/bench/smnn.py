"""S-MNN solver cost: forward + backward time and peak memory against sequence length T and batch size.

The shapes are those of Lorenz equation discovery (paper Table 1; spec §4.2): a batch of 50-step windows of the
three Lorenz variables, each variable its own 1-D ODE u' = r with O = 3 orders, steps 0.01, initial values at
t0, and the loss backpropagated to r and the initial values. Two left-hand-side modes:

- ``shared``: one coefficient set for the whole batch, as the S-MNN reference runs Lorenz (one factorisation,
  batch × 3 right-hand sides);
- ``per_sample``: one learnable left-hand side per window and variable (batch × 3 matrices), as mech-nn's
  dense MNN runs it, and as a forecaster whose encoder writes the coefficients does.

Solvers: ``banded`` (sequential blocked LDLᵀ), ``cyclic`` (block cyclic reduction), ``dense`` (the same system
with a dense Cholesky) and ``mnn`` (the original MNN with its slack variable). The dense ones estimate their
memory first and are refused, with the estimate in the row, beyond `dense_budget_gib`.
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from mpsim.bench.common import Suite, peak_memory_mb, scaling_exponent, timeit
from mpsim.solvers.mnn_dense import DenseSizeError, dense_solve, mnn_dense_solve
from mpsim.solvers.smnn import smnn_solve

SOLVERS = ("banded", "cyclic", "dense", "mnn")
SOLVER_NAMES = {
    "banded": "S-MNN banded",
    "cyclic": "S-MNN cyclic reduction",
    "dense": "S-MNN dense",
    "mnn": "MNN dense (slack)",
}
LHS_MODES = ("shared", "per_sample")


def lorenz_inputs(
    batch: int, length: int, lhs: str, n_orders: int = 3, seed: int = 0
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(coefficients [1 or batch, 3, 1, 1, 1, O], rhs [batch, 3, T, 1], init [batch, 3, 1, 1, 1]), float64,
    with gradients on everything a model would learn."""
    g = torch.Generator().manual_seed(seed)
    coef = torch.zeros(1, 1, 1, 1, 1, n_orders, dtype=torch.float64)
    coef[..., 1] = 1.0  # u' = r
    if lhs == "per_sample":
        coef = coef.expand(batch, 3, 1, 1, 1, n_orders).clone()
    rhs = torch.randn(batch, 3, length, 1, generator=g, dtype=torch.float64)
    init = torch.randn(batch, 3, 1, 1, 1, generator=g, dtype=torch.float64)
    return coef.requires_grad_(lhs == "per_sample"), rhs.requires_grad_(), init.requires_grad_()


def fwd_bwd(method: str, batch: int, length: int, lhs: str, n_orders: int, max_bytes: int) -> None:
    """One forward + backward pass of `method` on fresh Lorenz-shaped inputs (module level: picklable; the
    peak-memory measurement, which counts the inputs as a model's step would)."""
    solve_and_backward(method, *lorenz_inputs(batch, length, lhs, n_orders), max_bytes)


def solve_and_backward(
    method: str,
    coef: torch.Tensor,  # [1 or batch, 3, 1, 1, 1, O] coefficients
    rhs: torch.Tensor,  # [batch, 3, T, 1] right-hand sides
    init: torch.Tensor,  # [batch, 3, 1, 1, 1] initial values
    max_bytes: int,
) -> None:
    """Forward + backward of one solver on given inputs (what is timed: generating the random inputs is not)."""
    for x in (coef, rhs, init):
        x.grad = None
    if method == "dense":
        u = dense_solve(coef, rhs, init, 0.01, max_bytes=max_bytes, check=False)
    elif method == "mnn":
        u = mnn_dense_solve(coef, rhs, init, 0.01, max_bytes=max_bytes)[0]
    else:
        u = smnn_solve(coef, rhs, init, 0.01, method=method, check=False)
    u[..., 0].pow(2).sum().backward()


class SMNNBench(Suite):
    """Args:
    lengths: sequence lengths T, measured at batch `base_batch`.
    batches: batch sizes, measured at length `base_length`.
    base_batch: the batch of the T sweep (paper: 512).
    base_length: the T of the batch sweep (paper: 50).
    full_grid: measure every (batch, T) pair instead of the two sweeps.
    methods: solvers to measure (banded, cyclic, dense, mnn).
    lhs_modes: shared and/or per_sample left-hand sides.
    n_orders: derivative orders O (reference 3).
    dense_budget_gib: memory the dense solvers may use; beyond it a case is refused (and the row says why).
    repeats: timing repeats per case (fewer when a case is slow).
    memory: also measure the peak memory of each case in a fresh process (doubles the run time).
    fit_from: smallest T (and batch) in the fitted time exponents (tiny sizes measure dispatch overhead).
    fit_memory_from: smallest T in the fitted memory exponents (the peak is the resident-memory growth of a
        fresh process; below a few MiB it measures the allocator, not the solver).
    per_sample_max_length: per-sample cases with a longer T are not run (the sequential per-step LAPACK
        calls on batch x 3 tiny matrices take ~30 s at T = 5000 on a CPU); null runs them all.
    """

    name = "smnn"

    def __init__(
        self,
        lengths: Sequence[int] = (5, 50, 500, 5000, 10000),
        batches: Sequence[int] = (64, 512, 4096),
        base_batch: int = 512,
        base_length: int = 50,
        full_grid: bool = False,
        methods: Sequence[str] = SOLVERS,
        lhs_modes: Sequence[str] = LHS_MODES,
        n_orders: int = 3,
        dense_budget_gib: float = 4.0,
        repeats: int = 3,
        memory: bool = True,
        fit_from: int = 500,
        fit_memory_from: int = 500,
        per_sample_max_length: int | None = 500,
    ) -> None:
        bad = [m for m in methods if m not in SOLVERS] + [m for m in lhs_modes if m not in LHS_MODES]
        if bad:
            raise ValueError(f"bench.methods must be among {SOLVERS} and bench.lhs_modes among {LHS_MODES}; got {bad}.")
        self.lengths, self.batches = [int(n) for n in lengths], [int(b) for b in batches]
        self.base_batch, self.base_length, self.full_grid = int(base_batch), int(base_length), bool(full_grid)
        self.methods, self.lhs_modes, self.n_orders = list(methods), list(lhs_modes), int(n_orders)
        self.max_bytes = int(dense_budget_gib * 2**30)
        self.repeats, self.memory, self.fit_from = int(repeats), bool(memory), int(fit_from)
        self.fit_memory_from, self.per_sample_max_length = int(fit_memory_from), per_sample_max_length
        self.load: tuple[float, float] | None = None

    def cases(self) -> list[tuple[int, int]]:
        """(batch, T) pairs: the T sweep at base_batch, then the batch sweep at base_length (paper Table 1)."""
        if self.full_grid:
            return [(b, n) for b in self.batches for n in self.lengths]
        pairs = [(self.base_batch, n) for n in self.lengths] + [(b, self.base_length) for b in self.batches]
        return list(dict.fromkeys(pairs))

    def run(self) -> list[dict[str, Any]]:
        before = os.getloadavg()[0]  # the machine is shared: say how busy it was
        rows = []
        for lhs in self.lhs_modes:
            for batch, length in self.cases():
                if lhs == "per_sample" and self.per_sample_max_length and length > self.per_sample_max_length:
                    continue
                for method in self.methods:
                    rows.append(self._measure(method, batch, length, lhs))
        self.load = (before, os.getloadavg()[0])
        return rows

    def _measure(self, method: str, batch: int, length: int, lhs: str) -> dict[str, Any]:
        fn = functools.partial(fwd_bwd, method, batch, length, lhs, self.n_orders, self.max_bytes)
        row: dict[str, Any] = {
            "lhs": lhs,
            "method": method,
            "batch": batch,
            "T": length,
            "status": "ok",
            "fwd_bwd_ms": math.nan,
            "peak_mib": math.nan,
        }
        inputs = lorenz_inputs(batch, length, lhs, self.n_orders)
        step = functools.partial(solve_and_backward, method, *inputs, self.max_bytes)
        try:
            # two warm-up calls: the first ones grow the heap that later calls reuse (see `mpsim._keep_freed_cpu_memory`)
            stats = timeit(step, repeats=self.repeats, warmup=2, max_seconds=20.0)
        except DenseSizeError as err:
            row["status"] = (
                f"refused: needs {err.need_bytes / 2**30:.1f} GiB (budget {err.limit_bytes / 2**30:.1f} GiB)"
            )
            return row
        row["fwd_bwd_ms"] = 1e3 * stats["median_s"]
        if self.memory:
            # one thread in the forked child: OpenMP is not fork-safe once the parent has run a parallel region
            # (a child with 2 threads hangs), and the peak memory does not depend on the thread count
            row["peak_mib"] = peak_memory_mb(fn, threads=1)
        return row

    # ---- summary ---------------------------------------------------------------------------------------
    @staticmethod
    def _find(rows, **keys) -> dict[str, Any] | None:
        return next((r for r in rows if all(r[k] == v for k, v in keys.items()) and r["status"] == "ok"), None)

    def summarise(self, rows: list[dict[str, Any]]) -> list[str]:
        lines = []
        if self.load is not None:
            lines.append(
                f"- 1-minute load average {self.load[0]:.1f} before and {self.load[1]:.1f} after the run "
                f"on {os.cpu_count()} CPU(s): absolute times scale with it, ratios much less"
            )
        lines += ["", *self.table1(rows), "", *self.exponents(rows), ""]
        b0, t0 = self.base_batch, self.base_length
        for lhs in self.lhs_modes:
            fast = self._find(rows, lhs=lhs, method="banded", batch=b0, T=t0)
            for other in ("dense", "mnn", "cyclic"):
                slow = self._find(rows, lhs=lhs, method=other, batch=b0, T=t0)
                if fast and slow:
                    ratio = slow["fwd_bwd_ms"] / fast["fwd_bwd_ms"]
                    lines.append(
                        f"- {lhs} LHS, batch {b0}, T={t0}: banded is {ratio:.1f}× "
                        f"faster than {other} ({fast['fwd_bwd_ms']:.1f} vs {slow['fwd_bwd_ms']:.1f} ms)"
                    )
        fast = self._find(rows, lhs="shared", method="banded", batch=b0, T=t0)
        slow = self._find(rows, lhs="per_sample", method="mnn", batch=b0, T=t0)
        if fast and slow:  # paper Table 1: S-MNN with its frozen left-hand side vs mech-nn's dense MNN
            lines.append(
                f"- paper's comparison (S-MNN shared LHS vs dense MNN per sample), batch {b0}, T={t0}: "
                f"{slow['fwd_bwd_ms'] / fast['fwd_bwd_ms']:.0f}× faster"
            )
        for r in rows:
            if r["status"] != "ok":
                lines.append(f"- {r['method']} ({r['lhs']} LHS) at batch {r['batch']}, T={r['T']}: {r['status']}")
        for length in sorted(n for n in self.lengths if n >= 5000):
            for method in ("banded", "cyclic"):
                found = self._find(rows, lhs="shared", method=method, batch=b0, T=length)
                if found:
                    lines.append(
                        f"- T={length}, batch {b0}, shared LHS: {method} {found['fwd_bwd_ms'] / 1e3:.2f} s "
                        f"forward + backward, peak {found['peak_mib']:.0f} MiB"
                    )
        return lines

    def table1(self, rows: list[dict[str, Any]]) -> list[str]:
        """The paper's Table 1 layout: one column per (batch, T), time rows then memory rows per solver."""
        paper = [(512, 50), (512, 5), (512, 500), (64, 50), (4096, 50)]
        measured = list(dict.fromkeys((r["batch"], r["T"]) for r in rows))
        cols = [c for c in paper if c in measured] + [c for c in measured if c not in paper]
        series = list(dict.fromkeys((r["method"], r["lhs"]) for r in rows))
        head = "| (batch, T) | " + " | ".join(f"({b}, {t})" for b, t in cols) + " |"
        out = [
            "Forward + backward of the solver on the Lorenz discovery shapes (paper Table 1 layout; the paper "
            "times a whole optimisation step on an H100). —: not run.",
            "",
            head,
            "|---|" + "---|" * len(cols),
        ]
        for key, unit, fmt in (("fwd_bwd_ms", "time, ms", "{:.1f}"), ("peak_mib", "peak memory, MiB", "{:.0f}")):
            for method, lhs in series:
                cells = []
                for b, t in cols:
                    r = next(
                        (r for r in rows if (r["method"], r["lhs"], r["batch"], r["T"]) == (method, lhs, b, t)), None
                    )
                    if r is None:
                        cells.append("—")
                    elif r["status"] != "ok":
                        cells.append(r["status"].split(" (")[0].replace("refused: needs", "refused, needs"))
                    else:
                        cells.append(fmt.format(r[key]) if r[key] == r[key] else "—")
                label = f"{unit}: {SOLVER_NAMES[method]} ({lhs.replace('_', '-')} LHS)"
                out.append(f"| {label} | " + " | ".join(cells) + " |")
        return out

    def exponents(self, rows: list[dict[str, Any]]) -> list[str]:
        """Least-squares slopes of log(time) and log(memory) against log(T) at the base batch, and of log(time)
        against log(batch) at the base T."""
        b0, t0 = self.base_batch, self.base_length
        out = [
            f"Fitted scaling exponents (1 = linear): time over T ≥ {self.fit_from} and peak memory over "
            f"T ≥ {self.fit_memory_from} at batch {b0}, time over batch at T = {t0}.",
            "",
            "| solver | time ∝ T^k | memory ∝ T^k | time ∝ batch^k |",
            "|---|---|---|---|",
        ]
        for method, lhs in dict.fromkeys((r["method"], r["lhs"]) for r in rows):
            ok = [r for r in rows if r["method"] == method and r["lhs"] == lhs and r["status"] == "ok"]
            cells = []
            for key, axis, fixed, start in (
                ("fwd_bwd_ms", "T", ("batch", b0), self.fit_from),
                ("peak_mib", "T", ("batch", b0), self.fit_memory_from),
                ("fwd_bwd_ms", "batch", ("T", t0), 0),
            ):
                pts = sorted((r[axis], r[key]) for r in ok if r[fixed[0]] == fixed[1] and r[axis] >= start)
                k = scaling_exponent([p for p, _ in pts], [v for _, v in pts]) if len(pts) >= 2 else math.nan
                cells.append("—" if k != k else f"{k:.2f} ({axis} = {pts[0][0]}…{pts[-1][0]})")
            out.append(f"| {SOLVER_NAMES[method]} ({lhs.replace('_', '-')} LHS) | " + " | ".join(cells) + " |")
        return out

    def plot(self, rows: list[dict[str, Any]], out_dir: Path) -> list[str]:
        from mpsim.plotting import save_figure, subplots

        fig, axes = subplots(1, 3, figsize=(13, 3.8))
        for lhs, style in zip(self.lhs_modes, ("-", "--"), strict=False):
            for method in self.methods:
                label = f"{method} ({lhs})"
                by_t = sorted(
                    (r["T"], r["fwd_bwd_ms"], r["peak_mib"])
                    for r in rows
                    if r["lhs"] == lhs
                    and r["method"] == method
                    and r["batch"] == self.base_batch
                    and r["status"] == "ok"
                )
                by_b = sorted(
                    (r["batch"], r["fwd_bwd_ms"])
                    for r in rows
                    if r["lhs"] == lhs and r["method"] == method and r["T"] == self.base_length and r["status"] == "ok"
                )
                if by_t:
                    axes[0].loglog([p[0] for p in by_t], [p[1] for p in by_t], "o" + style, label=label)
                    axes[1].loglog([p[0] for p in by_t], [max(p[2], 1e-1) for p in by_t], "o" + style, label=label)
                if by_b:
                    axes[2].loglog([p[0] for p in by_b], [p[1] for p in by_b], "o" + style, label=label)
        axes[0].set(xlabel="sequence length T", ylabel="forward+backward (ms)", title=f"batch {self.base_batch}")
        axes[1].set(xlabel="sequence length T", ylabel="peak memory (MiB)", title=f"batch {self.base_batch}")
        axes[2].set(xlabel="batch", ylabel="forward+backward (ms)", title=f"T = {self.base_length}")
        axes[0].legend(fontsize=7)
        return [str(save_figure(fig, Path(out_dir) / "smnn_scaling.png"))]
