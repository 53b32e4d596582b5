"""S-MNN: the mechanistic-neural-network ODE layer as a linear-time block-banded least-squares solve.

Unknowns u[t, d, k] ≈ dᵏx_d/dtᵏ at T time points (D dims, O = K+1 orders, block size B = D·O per step).
The rows are governing equations Σ c·u = r (E per step), initial values on the first S steps and I orders,
and forward and backward Taylor smoothness rows between neighbouring steps, scaled by hⁱ (optionally central
rows). The normal matrix AᵀWA is block-tridiagonal (block-pentadiagonal with central rows); its blocks are
assembled directly from the coefficients and steps (never forming A), factorised by a blocked Cholesky/LDLᵀ
sweep over time ("banded") or by block cyclic reduction ("cyclic", `smnn_cyclic.py`), and differentiated
analytically: λ = (AᵀWA)⁻¹ g, dβ = λ, dA_ts = −(λ_t x_sᵀ + x_t λ_sᵀ), then autograd runs through the assembly.
Right-hand sides that share a left-hand side are solved as columns of one matrix (`smnn_layout.py`).
Formulas: `shared/reference/smnn_reference.md` §1-2 (Chen et al., Scalable Mechanistic Neural Networks).
"""

from __future__ import annotations

import math
from contextlib import contextmanager
from dataclasses import dataclass
from typing import NamedTuple

import torch

from mpsim.errors import MpsimError
from mpsim.solvers.banded import banded_factor, banded_solve
from mpsim.solvers.smnn_cyclic import cyclic_factor, cyclic_solve
from mpsim.solvers.smnn_layout import batch_to_columns, columns_to_output

METHODS = ("auto", "banded", "cyclic")


class SolverError(MpsimError, ValueError):
    """The S-MNN/MNN system is singular, not positive definite, too large, or its inputs are invalid."""


@dataclass
class SMNNProblem:
    """Validated inputs, step dimension first and every tensor with the same number of batch dims."""

    coefficients: torch.Tensor  # [T or 1, *batch_c, E, D, O]
    rhs: torch.Tensor  # [T or 1, *batch_r, E]
    init: torch.Tensor  # [S or 1, *batch_i, D, I]
    steps: torch.Tensor  # [T-1 or 1, *batch_s]
    n_steps: int  # T
    n_init_steps: int  # S
    weights: tuple[float, float, float]  # (equation, initial value, smoothness)
    central: bool
    batch: torch.Size  # broadcast of all batch shapes
    batch_lhs: torch.Size  # broadcast of coefficient and step batch shapes (padded to len(batch))

    @property
    def dims(self) -> tuple[int, int, int]:  # (E, D, O)
        e, d, o = self.coefficients.shape[-3:]
        return e, d, o


class Blocks(NamedTuple):
    """AᵀWA and AᵀWb in the solver layout: L = prod(batch_lhs) matrices, R right-hand sides per matrix."""

    a0: torch.Tensor  # [T, L, B, B] diagonal blocks
    a1: torch.Tensor  # [T-1, L, B, B] blocks (t+1, t)
    a2: torch.Tensor | None  # [T-2, L, B, B] blocks (t+2, t), central rows only
    beta: torch.Tensor  # [T, L, B, R] AᵀWb; see `batch_to_columns` for the batch -> (L, R) split


def prepare_problem(
    coefficients: torch.Tensor,  # [*batch, T or 1, E, D, O] (step dim first if step_dim_first)
    rhs_equation: torch.Tensor,  # [*batch, T or 1, E]
    init_vars: torch.Tensor,  # [*batch, S or 1, D, I]
    steps: torch.Tensor | float,  # [*batch, T-1 or 1]
    *,
    n_steps: int | None,
    n_init_var_steps: int | None,
    weights: tuple[float, float, float],
    central: bool,
    step_dim_first: bool,
    dtype: torch.dtype,
) -> SMNNProblem:
    """Check shapes, move the step dim first, infer T and S, and pad batch dims (see `smnn_solve`)."""
    if not isinstance(steps, torch.Tensor):
        steps = torch.tensor([float(steps)], dtype=dtype, device=coefficients.device)  # not float32
    specs = (
        ("coefficients", coefficients, 4, "[*batch, T, E, D, O]"),
        ("rhs_equation", rhs_equation, 2, "[*batch, T, E]"),
        ("init_vars", init_vars, 3, "[*batch, S, D, I]"),
        ("steps", steps, 1, "[*batch, T-1]"),
    )
    moved = []
    for name, x, core, shape in specs:
        if x.dim() < core:
            raise SolverError(
                f"{name} must have shape {shape} (step dim first when step_dim_first=True); got {tuple(x.shape)}."
            )
        moved.append((x if step_dim_first else x.movedim(-core, 0)).to(dtype))
    coef, rhs, init, h = moved
    n_batch = max(x.dim() - c for x, (_, _, c, _) in zip(moved, specs, strict=True))
    coef, rhs, init, h = (
        x.reshape(x.shape[0], *[1] * (n_batch - x.dim() + c), *x.shape[1:])
        for x, (_, _, c, _) in zip(moved, specs, strict=True)
    )
    E, D, O = coef.shape[-3:]
    if rhs.shape[-1] != E or init.shape[-2] != D or init.shape[-1] > O:
        raise SolverError(
            f"inconsistent sizes: coefficients give E={E}, D={D}, O={O}; rhs_equation has "
            f"E={rhs.shape[-1]}, init_vars has D={init.shape[-2]}, I={init.shape[-1]} "
            "(need I ≤ O)."
        )
    lengths = [n for n in (coef.shape[0], rhs.shape[0], h.shape[0] + 1 if h.shape[0] > 1 else 1) if n > 1]
    T = n_steps if n_steps is not None else (max(lengths) if lengths else 0)
    if T < 2:
        raise SolverError(
            f"S-MNN needs at least 2 time steps; got T={T}. Pass n_steps= when every input has a size-1 step dimension."
        )
    for name, n, want in (
        ("coefficients", coef.shape[0], T),
        ("rhs_equation", rhs.shape[0], T),
        ("steps", h.shape[0], T - 1),
    ):
        if n not in (1, want):
            raise SolverError(f"{name} has {n} entries along the step dim; expected 1 or {want} (T={T}).")
    S = n_init_var_steps if n_init_var_steps is not None else init.shape[0]
    if S > T or (S > 0 and init.shape[0] not in (1, S)):
        raise SolverError(
            f"init_vars has {init.shape[0]} steps; cannot use it for S={S} initial steps of "
            f"T={T} (need 1 or S steps, S ≤ T)."
        )
    if central and O < 2:
        raise SolverError("central=True needs n_orders ≥ 2 (the central rows use orders K-1 and K).")
    if any(w < 0 for w in weights):
        raise SolverError(f"weights must be ≥ 0; got {weights}.")
    if not bool((torch.isfinite(h) & (h > 0)).all()):
        raise SolverError(
            f"steps must be finite and > 0; got min {h.min().item():.3g}. Parametrise learned "
            "steps through a sigmoid/softplus with a floor."
        )
    batch_shapes = [x.shape[1 : 1 + n_batch] for x in (coef, rhs, init, h)]
    try:
        batch = torch.broadcast_shapes(*batch_shapes)
    except RuntimeError as err:
        raise SolverError(f"batch shapes do not broadcast: {[tuple(b) for b in batch_shapes]}.") from err
    batch_lhs = torch.broadcast_shapes(batch_shapes[0], batch_shapes[3])
    return SMNNProblem(coef, rhs, init, h, T, S, weights, central, batch, batch_lhs)


def _pad_time(x: torch.Tensor, before: int, after: int) -> torch.Tensor:
    """Zero-pad dim 0 (time)."""
    parts = [x.new_zeros((before, *x.shape[1:])), x, x.new_zeros((after, *x.shape[1:]))]
    return torch.cat(parts)


def _kron_dims(block: torch.Tensor, D: int) -> torch.Tensor:
    """I_D ⊗ block: smoothness never couples dimensions. [..., O, O] -> [..., D·O, D·O]."""
    eye = torch.eye(D, dtype=block.dtype, device=block.device)
    out = eye[:, None, :, None] * block[..., None, :, None, :]
    return out.reshape(*block.shape[:-2], D * block.shape[-1], D * block.shape[-1])


def taylor_matrix(O: int, dtype: torch.dtype, device: torch.device | None = None) -> torch.Tensor:
    """F[i, j] = 1/(j-i)! for j ≥ i, else 0 (the Taylor weights between derivative orders). [O, O]"""
    diff = torch.arange(O, device=device)[None, :] - torch.arange(O, device=device)[:, None]
    return torch.where(diff >= 0, torch.exp(-torch.lgamma(diff.clamp(min=0) + 1.0)), 0.0).to(dtype)


def assemble_blocks(prob: SMNNProblem) -> Blocks:
    """The blocks of AᵀWA and AᵀWb (spec §2.1), differentiable w.r.t. all inputs."""
    T, S = prob.n_steps, prob.n_init_steps
    E, D, O = prob.dims
    B, K = D * O, O - 1
    w_e, w_i, w_s = prob.weights
    dt, dev = prob.coefficients.dtype, prob.coefficients.device
    h = prob.steps.expand(T - 1, *prob.steps.shape[1:])  # [T-1, *batch_s]
    orders = torch.arange(O, device=dev)
    F = taylor_matrix(O, dt, dev)
    keep = torch.ones(O, dtype=dt, device=dev)
    if prob.central:  # FWD/BWD rows stop at order K-1; the central rows take over the top order
        F[K, K] = 0.0
        keep[K] = 0.0
    sign = (-1.0) ** orders.to(dt)
    sign2 = sign[:, None] * sign[None, :]
    e = w_s * h[..., None] ** orders  # [T-1, *bs, O]: e_{t,k} = w_s h_t^k
    P = e[..., :, None] * e[..., None, :]
    Q = P * (F.mT @ F)
    diag_e2 = torch.diag_embed(e**2 * keep)
    # FWD row of step t touches u_t through Q and u_{t+1} through e²; BWD mirrors it (sign on odd orders)
    S0 = _pad_time(Q + diag_e2, 0, 1) + _pad_time(sign2 * Q + diag_e2, 1, 0)
    S1 = -P * (F + sign2 * F.mT)
    S2 = None
    if prob.central:
        H = h[:-1] + h[1:]  # [T-2, *bs]
        a, b, c = (w_s**2 * H ** (2 * K + p) for p in (-4, -3, -2))
        unit = torch.eye(O, dtype=dt, device=dev)
        e_mm, e_tt = unit[K - 1][:, None] * unit[K - 1], unit[K][:, None] * unit[K]
        e_tm = unit[K][:, None] * unit[K - 1]  # entry (K, K-1)
        S0 = S0 + (_pad_time(a, 0, 2) + _pad_time(a, 2, 0))[..., None, None] * e_mm
        S0 = S0 + _pad_time(c, 1, 1)[..., None, None] * e_tt
        S1 = S1 + _pad_time(b, 0, 1)[..., None, None] * e_tm - _pad_time(b, 1, 0)[..., None, None] * e_tm.mT
        S2 = -a[..., None, None] * e_mm
    # equation rows: C_t is coefficients[t] flattened d-major, matching the unknown index d·O + k
    C = prob.coefficients.reshape(*prob.coefficients.shape[:-2], B)  # [T or 1, *bc, E, B]
    iv_mask = (
        ((torch.arange(T, device=dev) < S)[:, None, None] & (orders < prob.init.shape[-1])[None, None, :])
        .expand(T, D, O)
        .reshape(T, B)
    )
    iv_diag = torch.diag_embed(w_i**2 * iv_mask.to(dt)).reshape(T, *[1] * len(prob.batch), B, B)
    bl, L = prob.batch_lhs, math.prod(prob.batch_lhs)
    a0 = (w_e**2 * (C.mT @ C) + iv_diag + _kron_dims(S0, D)).expand(T, *bl, B, B).reshape(T, L, B, B)
    a1 = _kron_dims(S1, D).expand(T - 1, *bl, B, B).reshape(T - 1, L, B, B)
    a2 = None if S2 is None else _kron_dims(S2, D).expand(T - 2, *bl, B, B).reshape(T - 2, L, B, B)
    # AᵀWb straight into the (L, R) layout: the right-hand sides are the large tensors (R = batch/L columns),
    # so they are permuted while they are still E- or I-sized and every later step runs on that layout
    C = (w_e**2 * C).expand(C.shape[0], *bl, E, B).reshape(C.shape[0], L, E, B)
    beta = C.mT @ batch_to_columns(prob.rhs, bl, prob.batch)  # [T or 1, L, B, R]
    n_iv = prob.init.shape[-1]
    if S > 0 and n_iv > 0 and w_i > 0:  # initial values enter only the first S steps
        v = prob.init.expand(S, *prob.init.shape[1:])
        v = torch.nn.functional.pad(v, (0, O - n_iv)).reshape(S, *v.shape[1:-2], B)  # orders ≥ I: no value
        v = w_i**2 * batch_to_columns(v, bl, prob.batch)
        if beta.shape[0] == T:  # beta is a fresh matmul result: add in place (a full copy costs ~0.1 s at Lorenz
            beta = AddHead.apply(beta, v)  # T = 5000, batch 512), with a pass-through backward
        else:  # broadcast over time: materialise it once, with the initial values added
            beta = torch.index_add(beta.expand(T, *beta.shape[1:]), 0, torch.arange(S, device=dev), v)
    return Blocks(a0, a1, a2, beta.expand(T, *beta.shape[1:]))


class AddHead(torch.autograd.Function):
    """x[:S] += head in place on a fresh intermediate; the backward passes the gradient through unchanged
    (no copy: an out-of-place add or an autograd-tracked in-place slice add both copy the whole tensor)."""

    @staticmethod
    def forward(ctx, x, head):  # x: [T, ...] (not saved by any backward), head: [S, ...]
        x[: head.shape[0]] += head
        ctx.mark_dirty(x)
        ctx.n_head = head.shape[0]
        return x

    @staticmethod
    def backward(ctx, grad):
        return grad, grad[: ctx.n_head]


def check_determined(prob: SMNNProblem, tol: float = 1e-11) -> None:
    """Raise a `SolverError` naming the missing rows if EQ and IV rows leave the system singular.

    The smoothness rows are satisfied exactly by every polynomial of degree ≤ K in each dimension (Taylor
    expansion is exact for them), so AᵀWA is positive definite iff the equation and initial-value rows
    restricted to that B-dimensional space have full rank. We test the Jacobi-scaled B×B Gram matrix of those
    rows on a centred, length-normalised polynomial basis; its eigenvectors say which terms are free.
    """
    T, S = prob.n_steps, prob.n_init_steps
    E, D, O = prob.dims
    w_e, w_i, _ = prob.weights
    with torch.no_grad():
        h = prob.steps.expand(T - 1, *prob.steps.shape[1:])
        tau = _pad_time(torch.cumsum(h, 0), 1, 0)  # [T, *bs] time of each step
        span = tau[-1]
        s = (tau - 0.5 * span) / span
        k = torch.arange(O, device=h.device)
        power = k[None, :] - k[:, None]  # row: derivative order k, column: polynomial degree j
        falling = torch.exp(torch.lgamma(k[None, :] + 1.0) - torch.lgamma(power.clamp(min=0) + 1.0))
        basis = torch.where(power >= 0, falling * s[..., None, None] ** power.clamp(min=0), 0.0)
        basis = basis / span[..., None, None] ** k[:, None]  # [T, *bs, O(k), O(j)]: d^k/dτ^k s(τ)^j
        cn = (prob.coefficients @ basis.unsqueeze(-3)).reshape(T, *prob.batch_lhs, E, D * O)
        gram = w_e**2 * (cn.mT @ cn).sum(0)
        n_iv = prob.init.shape[-1] if S > 0 else 0
        iv = basis[:S, ..., :n_iv, :]
        gram = gram + w_i**2 * _kron_dims((iv.mT @ iv).sum(0), D)  # [*batch_lhs, B, B]
        if not bool(torch.isfinite(gram).all()):
            raise SolverError("coefficients or steps contain NaN/inf; the S-MNN system is undefined.")
        g = torch.diagonal(gram, dim1=-2, dim2=-1)
        inv = torch.where(g > 0, g.clamp(min=1e-300).rsqrt(), 0.0)
        eig, vec = torch.linalg.eigh(gram * inv[..., :, None] * inv[..., None, :])
        bad = eig[..., 0] < tol
        if not bool(bad.any()):
            return
    idx = tuple(int(i) for i in torch.nonzero(bad)[0])
    # free polynomials (undo the Jacobi scaling), described by their value and derivatives at the first step:
    # a polynomial of degree ≤ K is fixed by those, so these are the initial conditions nothing determines
    null = torch.where(g[idx] > 0, inv[idx], 1.0)[:, None] * vec[idx][:, eig[idx] < tol]  # [B, n_free]
    at_start = _kron_dims(basis[0].expand(*prob.batch_lhs, O, O)[idx], D) @ null
    weight = at_start.norm(dim=-1).reshape(D, O)
    order_name = {0: "value", 1: "first derivative", 2: "second derivative"}
    terms = [
        f"dimension {d}: "
        + ", ".join(
            order_name.get(k, f"derivative of order {k}") for k in range(O) if weight[d, k] > 1e-6 * weight.max()
        )
        for d in range(D)
        if weight[d].max() > 1e-6 * weight.max()
    ]
    has_iv = S > 0 and n_iv > 0 and w_i > 0
    has_eq = E > 0 and w_e > 0 and bool(prob.coefficients.ne(0).any())
    missing = [m for m, ok in (("initial-value rows", has_iv), ("governing-equation rows", has_eq)) if not ok]
    why = (
        f"there are no {' and no '.join(missing)}"
        if missing
        else f"the equation rows (E={E}) and initial values (S={S} steps x I={n_iv} orders) do not fix them"
    )
    raise SolverError(
        f"S-MNN system is singular (left-hand side batch index {idx}): {null.shape[1]} solution "
        f"direction(s) are free, undetermined at the first step: {'; '.join(terms)}. The smoothness rows "
        f"are satisfied exactly by any polynomial of degree ≤ {O - 1}, so equation and initial-value rows "
        f"must pin these down, but {why}. Fix: pass init_vars with these orders (I) or on more initial "
        "steps (S), or equation rows involving them."
    )


_BACKENDS = {"banded": (banded_factor, banded_solve), "cyclic": (cyclic_factor, cyclic_solve)}


@contextmanager
def _single_threaded(enabled: bool):
    """Run tiny-block LAPACK calls on one thread.

    MKL threads each small potrf/trsm call; with B×B blocks of a few rows the fork/join costs 10-100x the
    arithmetic (a batched Cholesky of 512 3×3 blocks: 0.05 ms on one thread, 15 ms on two busy cores).
    """
    n = torch.get_num_threads()
    if not enabled or n == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


class BlockSPDSolve(torch.autograd.Function):
    """x = M⁻¹ β for the symmetric block-banded M given by its lower blocks; analytic backward (spec §2.4)."""

    @staticmethod
    def forward(ctx, a0, a1, a2, beta, method):  # shapes as in `Blocks`
        factor, solve = _BACKENDS[method]
        with _single_threaded(a0.device.type == "cpu"):
            # cyclic: the chunk length depends on how much data a time step carries (see `chunk_length`)
            fac, bad = factor(a0, a1, a2, width=beta.shape[-1]) if method == "cyclic" else factor(a0, a1, a2)
        if bool(bad.any()):
            raise SolverError(
                f"S-MNN normal matrix is not positive definite for {int(bad.sum())} of {bad.numel()} "
                f"left-hand sides (first: flat index {int(torch.nonzero(bad)[0])}): a Cholesky pivot block "
                "failed. Check for NaN/inf coefficients or steps, and that the equation and initial-value "
                "rows determine the solution (call with check=True for a diagnosis)."
            )
        with _single_threaded(a0.device.type == "cpu"):
            x = solve(fac, beta)
        ctx.fac, ctx.method = fac, method
        ctx.save_for_backward(a0, a1, a2, x)
        return x

    @staticmethod
    def backward(ctx, grad_x):
        a0, a1, a2, x = ctx.saved_tensors
        if torch.is_grad_enabled():  # double backward: keep the adjoint solve differentiable
            lam = BlockSPDSolve.apply(a0, a1, a2, grad_x, ctx.method)
        else:  # the matrix is symmetric, so the adjoint solve reuses the forward factors
            with _single_threaded(x.device.type == "cpu"):
                if ctx.method == "cyclic":  # gradients need no refinement to 1e-11; saves half the backward
                    lam = cyclic_solve(ctx.fac, grad_x, refine=0)
                else:
                    lam = banded_solve(ctx.fac, grad_x.contiguous())
        # d(M⁻¹β)/dM = −λxᵀ; each stored lower block also stands for its transpose above the diagonal.
        # The matmul over the R right-hand-side columns sums the broadcast gradient down to each matrix.
        need = ctx.needs_input_grad
        g0 = -(lam @ x.mT) if need[0] else None
        g1 = -(lam[1:] @ x[:-1].mT + x[1:] @ lam[:-1].mT) if need[1] else None
        g2 = -(lam[2:] @ x[:-2].mT + x[2:] @ lam[:-2].mT) if a2 is not None and need[2] else None
        return g0, g1, g2, lam, None


def choose_method(n_lhs: int, block: int, n_rhs: int, device: torch.device, n_steps: int | None = None) -> str:
    """The faster backend for a problem shape ("auto").

    On a CPU the sequential sweep pays ~10 µs of dispatch per operation and step (about 9 per step for a
    forward + backward), which chunked cyclic reduction avoids. Measured forward + backward on 2 busy CPU cores
    (one trajectory, D = 3, O = 3, time-varying coefficients): cyclic 2.3x faster at T = 1000, 3.7x at T = 5000,
    banded 1.3x faster at T = 100. With one small shared matrix and many right-hand sides (Lorenz discovery
    shapes, 1536 columns; `mpsim bench bench=smnn`) banded wins at T = 50 (10 vs 15 ms) and both are bound by
    memory traffic from T ≈ 500 on (T = 5000: 0.77 vs 0.87 s, T = 10 000: 1.66 vs 1.73 s, once freed memory is
    reused rather than faulted in again: see `mpsim._keep_freed_cpu_memory`). With many matrices (one per
    sample) the factorisation dominates and cyclic reduction's extra Schur-complement work makes banded faster
    (T = 500: 1.1 vs 1.7 s).
    On a GPU the launch overhead dominates even more, so cyclic reduction is taken there (not benchmarked).
    """
    if device.type != "cpu":
        return "cyclic"
    if n_steps is not None and n_steps < 256:
        return "banded"
    thin = n_lhs * block * (block + n_rhs) < 2048  # little data per step: dispatch-bound at any T ≥ 256
    cheap_factor = n_lhs * block * block <= 1024  # few small matrices: dispatch-bound once T is long
    return "cyclic" if thin or (cheap_factor and n_steps is not None and n_steps >= 1000) else "banded"


def smnn_solve(
    coefficients: torch.Tensor,  # [*batch, T or 1, E, D, O] equation coefficients c_{t,e,d,k}
    rhs_equation: torch.Tensor,  # [*batch, T or 1, E] equation right-hand sides r_{t,e}
    init_vars: torch.Tensor,  # [*batch, S or 1, D, I] initial values of orders < I on the first S steps
    steps: torch.Tensor | float,  # [*batch, T-1 or 1] step sizes h_t (> 0)
    *,
    n_steps: int | None = None,
    n_init_var_steps: int | None = None,
    weight_equation: float = 1.0,
    weight_init_var: float = 1.0,
    weight_smooth: float = 1.0,
    central: bool = False,
    method: str = "auto",
    step_dim_first: bool = False,
    check: bool = True,
    dtype: torch.dtype = torch.float64,
) -> torch.Tensor:  # [*batch, T, D, O]
    """Solve the S-MNN least-squares ODE system (AᵀWA) u = AᵀWb in time and memory linear in T.

    All batch shapes broadcast against each other; the matrix is factorised once per element of
    batch_lhs = broadcast(batch of coefficients, batch of steps) and shared by all right-hand sides, so a
    constant-coefficient layer (Lorenz discovery) costs one factorisation for the whole batch.

    Args:
        coefficients: c in Σ_{d,k} c_{t,e,d,k} u_{t,d,k} = r_{t,e}; a size-1 step dim is shared by all steps.
        rhs_equation: r, likewise broadcast over steps when its step dim has size 1.
        init_vars: v in u_{s,d,k} = v_{s,d,k} for s < S, k < I (I = 0 or S = 0: no initial values).
        steps: step sizes between consecutive time points (a float is one shared step).
        n_steps: T when every input has a size-1 step dim; otherwise inferred.
        n_init_var_steps: S; defaults to the size of the step dim of init_vars.
        weight_equation: w_e, weight of the equation rows (W = w², as in the reference).
        weight_init_var: w_i, weight of the initial-value rows.
        weight_smooth: w_s, weight of the smoothness rows.
        central: use central smoothness rows for the top order (block-pentadiagonal matrix).
        method: "banded" (sequential blocked LDLᵀ over time, the reference algorithm), "cyclic" (block
            cyclic reduction, O(log T) sequential depth; faster when each step carries little data), or
            "auto" (pick by `choose_method`). Both give the same answer to ~1e-11 relative.
        step_dim_first: inputs given as [T, *batch, ...] (the reference layout) instead of batch first.
        check: first test that equation and initial-value rows make the system non-singular (cheap, O(T)).
        dtype: compute dtype; float64 is needed (cond(AᵀWA) ~ 1/h^{2K}). The result has the inputs' dtype.

    Returns:
        u[..., t, d, k] ≈ dᵏx_d/dtᵏ at step t: a strided view of the solver's buffer, in which each step's
        values over the right-hand-side batch dims are contiguous (call `.contiguous()` if a layout matters).

    Raises:
        SolverError: invalid shapes or steps, a singular system (with the rows that are missing), or a
            non-positive-definite factorisation.
    """
    if method not in METHODS:
        raise SolverError(f'Invalid method "{method}". Must be one of {METHODS}.')
    out_dtype = torch.promote_types(coefficients.dtype, rhs_equation.dtype)
    prob = prepare_problem(
        coefficients,
        rhs_equation,
        init_vars,
        steps,
        n_steps=n_steps,
        n_init_var_steps=n_init_var_steps,
        central=central,
        step_dim_first=step_dim_first,
        weights=(weight_equation, weight_init_var, weight_smooth),
        dtype=dtype,
    )
    if check:
        check_determined(prob)
    a0, a1, a2, beta = assemble_blocks(prob)
    if method == "auto":
        method = choose_method(a0.shape[1], a0.shape[-1], beta.shape[-1], a0.device, a0.shape[0])
    x = BlockSPDSolve.apply(a0, a1, a2, beta, method)
    if not bool(torch.isfinite(x.sum())):  # one reduction instead of an elementwise pass
        raise SolverError(
            "S-MNN solution is not finite: check coefficients, rhs_equation, init_vars and steps for NaN/inf."
        )
    u = columns_to_output(x, prob.batch_lhs, prob.batch)  # [*batch, T, B], a view of the solution
    return u.unflatten(-1, prob.dims[1:]).to(out_dtype)
