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
    """One forward + backward pass of `method` on fresh Lorenz-shaped inputs (module level: picklable)."""
    coef, rhs, init = lorenz_inputs(batch, length, lhs, n_orders)
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
    fit_memory_from: smallest T in the fitted memory exponents. The peak is measured as resident-memory growth
        of a forked process, which is only reliable when the tensors exceed glibc's mmap threshold (32 MB,
        T ≳ 2000 at batch 512): smaller ones reuse heap pages the parent already holds and barely register.
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
        fit_from: int = 50,
        fit_memory_from: int = 5000,
        per_sample_max_length: int | None = 500,
    ) -> None:
        bad = [m for m in methods if m not in SOLVERS] + [m for m in lhs_modes if m not in LHS_MODES]
        if bad:
            raise ValueError(f"bench.methods must be among {SOLVERS} and bench.lhs_modes among {LHS_MODES}; "
                             f"got {bad}.")
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
        row: dict[str, Any] = {"lhs": lhs, "method": method, "batch": batch, "T": length, "status": "ok",
                               "fwd_bwd_ms": math.nan, "peak_mib": math.nan}
        try:
            stats = timeit(fn, repeats=self.repeats, warmup=1, max_seconds=20.0)
        except DenseSizeError as err:
            row["status"] = (f"refused: needs {err.need_bytes / 2**30:.1f} GiB "
                             f"(budget {err.limit_bytes / 2**30:.1f} GiB)")
            return row
        row["fwd_bwd_ms"] = 1e3 * stats["median_s"]
        if self.memory:
            row["peak_mib"] = peak_memory_mb(fn, threads=torch.get_num_threads())
        return row

    # ---- summary ---------------------------------------------------------------------------------------
    @staticmethod
    def _find(rows, **keys) -> dict[str, Any] | None:
        return next((r for r in rows if all(r[k] == v for k, v in keys.items()) and r["status"] == "ok"), None)

    def summarise(self, rows: list[dict[str, Any]]) -> list[str]:
        lines = []
        if self.load is not None:
            lines.append(f"- 1-minute load average {self.load[0]:.1f} before and {self.load[1]:.1f} after the run "
                         f"on {os.cpu_count()} CPU(s): absolute times scale with it, ratios much less")
        b0, t0 = self.base_batch, self.base_length
        for lhs in self.lhs_modes:
            fast = self._find(rows, lhs=lhs, method="banded", batch=b0, T=t0)
            for other in ("dense", "mnn", "cyclic"):
                slow = self._find(rows, lhs=lhs, method=other, batch=b0, T=t0)
                if fast and slow:
                    lines.append(f"- {lhs} LHS, batch {b0}, T={t0}: banded is {slow['fwd_bwd_ms'] / fast['fwd_bwd_ms']:.1f}× "
                                 f"faster than {other} ({fast['fwd_bwd_ms']:.1f} vs {slow['fwd_bwd_ms']:.1f} ms)")
            for method in self.methods:
                for key, unit, start in (("fwd_bwd_ms", "time", self.fit_from),
                                         ("peak_mib", "peak memory", self.fit_memory_from)):
                    sweep = sorted((r["T"], r[key]) for r in rows if r["lhs"] == lhs and r["method"] == method
                                   and r["batch"] == b0 and r["status"] == "ok" and r["T"] >= start)
                    if len(sweep) >= 2:
                        k = scaling_exponent([s for s, _ in sweep], [v for _, v in sweep])
                        lines.append(f"- {lhs} LHS, {method}: {unit} ∝ T^{k:.2f} (batch {b0}, T = {sweep[0][0]}…"
                                     f"{sweep[-1][0]})")
                sweep = sorted((r["batch"], r["fwd_bwd_ms"]) for r in rows if r["lhs"] == lhs and r["method"] == method
                               and r["T"] == t0 and r["status"] == "ok")
                if len(sweep) >= 2:
                    k = scaling_exponent([s for s, _ in sweep], [v for _, v in sweep])
                    lines.append(f"- {lhs} LHS, {method}: time ∝ batch^{k:.2f} (T={t0}, batch {sweep[0][0]}…"
                                 f"{sweep[-1][0]})")
        fast = self._find(rows, lhs="shared", method="banded", batch=b0, T=t0)
        slow = self._find(rows, lhs="per_sample", method="mnn", batch=b0, T=t0)
        if fast and slow:  # paper Table 1: S-MNN with its frozen left-hand side vs mech-nn's dense MNN
            lines.append(f"- paper's comparison (S-MNN shared LHS vs dense MNN per sample), batch {b0}, T={t0}: "
                         f"{slow['fwd_bwd_ms'] / fast['fwd_bwd_ms']:.0f}× faster")
        for r in rows:
            if r["status"] != "ok":
                lines.append(f"- {r['method']} ({r['lhs']} LHS) at batch {r['batch']}, T={r['T']}: {r['status']}")
        for length in sorted(n for n in self.lengths if n >= 5000):
            for method in ("banded", "cyclic"):
                r = self._find(rows, lhs="shared", method=method, batch=b0, T=length)
                if r:
                    lines.append(f"- T={length}, batch {b0}, shared LHS: {method} {r['fwd_bwd_ms'] / 1e3:.2f} s "
                                 f"forward + backward, peak {r['peak_mib']:.0f} MiB")
        return lines

    def plot(self, rows: list[dict[str, Any]], out_dir: Path) -> list[str]:
        import matplotlib.pyplot as plt

        from mpsim.plotting import _save

        fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
        for lhs, style in zip(self.lhs_modes, ("-", "--"), strict=False):
            for method in self.methods:
                label = f"{method} ({lhs})"
                by_t = sorted((r["T"], r["fwd_bwd_ms"], r["peak_mib"]) for r in rows if r["lhs"] == lhs
                              and r["method"] == method and r["batch"] == self.base_batch and r["status"] == "ok")
                by_b = sorted((r["batch"], r["fwd_bwd_ms"]) for r in rows if r["lhs"] == lhs
                              and r["method"] == method and r["T"] == self.base_length and r["status"] == "ok")
                if by_t:
                    axes[0].loglog([p[0] for p in by_t], [p[1] for p in by_t], "o" + style, label=label)
                    axes[1].loglog([p[0] for p in by_t], [max(p[2], 1e-1) for p in by_t], "o" + style, label=label)
                if by_b:
                    axes[2].loglog([p[0] for p in by_b], [p[1] for p in by_b], "o" + style, label=label)
        axes[0].set(xlabel="sequence length T", ylabel="forward+backward (ms)", title=f"batch {self.base_batch}")
        axes[1].set(xlabel="sequence length T", ylabel="peak memory (MiB)", title=f"batch {self.base_batch}")
        axes[2].set(xlabel="batch", ylabel="forward+backward (ms)", title=f"T = {self.base_length}")
        axes[0].legend(fontsize=7)
        return [str(_save(fig, Path(out_dir) / "smnn_scaling.png"))]
