"""Parallel-in-time block cyclic reduction for the S-MNN normal equations.

The banded LDLᵀ of `mpsim.solvers.smnn` walks the T time blocks one after another, so its cost is T times the
launch overhead of a few tiny kernels. Block cyclic reduction removes the odd-numbered time blocks by a Schur
complement, which leaves a block-tridiagonal SPD system on the even blocks of half the length; repeating this
⌈log₂ T⌉ times leaves one block. Every level is a handful of batched operations over all its blocks, so the
sequential depth is O(log T) and the work O(T·B³) (about twice the flops of the sequential sweep and 2-4x
its memory traffic on the right-hand sides).
For an SPD matrix this is Cholesky on an odd-even permutation of the unknowns, hence backward stable.

The block-pentadiagonal system of central smoothness rows is handled by pairing time steps (t = 2J, 2J+1)
into super-blocks of size 2B, which makes it block-tridiagonal again.

Layout (as in `smnn.py`): blocks are [T, L, B, B] with L independent left-hand sides (the flattened batch of
left-hand sides) and right-hand sides are [T, L, B, R] with R columns sharing each left-hand side. `A1[t]` is
the block (t+1, t) and `A2[t]` the block (t+2, t); only lower blocks are passed, the matrix is symmetric.
"""

from __future__ import annotations

from typing import NamedTuple

import torch


class Level(NamedTuple):
    """One reduction level: its odd blocks i = 2m+1 are x_i = D_i⁻¹ b_i − P_i x_{i−1} − N_i x_{i+1}."""

    dinv: torch.Tensor  # [n_odd, L, b, b] D_i⁻¹
    prev: torch.Tensor  # [n_odd, L, b, b] P_i = D_i⁻¹ · block (i, i−1)
    next: torch.Tensor  # [n_odd, L, b, b] N_i = D_i⁻¹ · block (i, i+1) (zero past the end)


class CyclicFactors(NamedTuple):
    levels: list[Level]  # finest first
    root_inv: torch.Tensor  # [1, L, b, b] inverse of the last remaining block
    paired: bool  # time steps were paired into 2B super-blocks (central rows)
    blocks: tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]  # original (A0, A1, A2), for refinement


def _zero_block(x: torch.Tensor) -> torch.Tensor:
    return x.new_zeros((1, *x.shape[1:]))


def _pair_pentadiagonal(
    A0: torch.Tensor,  # [T, L, B, B]
    A1: torch.Tensor,  # [T-1, L, B, B]
    A2: torch.Tensor,  # [T-2, L, B, B]
) -> tuple[torch.Tensor, torch.Tensor]:  # [T'/2, L, 2B, 2B] diagonal, [T'/2 - 1, L, 2B, 2B] sub-diagonal
    """Rewrite a block-pentadiagonal matrix as block-tridiagonal with 2B×2B super-blocks.

    An odd T is padded with one decoupled identity block, whose unknown is zero and is dropped afterwards.
    """
    B = A0.shape[-1]
    if A0.shape[0] % 2:
        A0 = torch.cat([A0, torch.eye(B, dtype=A0.dtype, device=A0.device).expand(1, *A0.shape[1:])])
        A1 = torch.cat([A1, _zero_block(A0)])
        A2 = torch.cat([A2, _zero_block(A0)])
    a0e, a0o, a1e = A0[0::2], A0[1::2], A1[0::2]  # diagonal blocks of super-block J and its inner coupling
    diag = torch.cat([torch.cat([a0e, a1e.mT], -1), torch.cat([a1e, a0o], -1)], -2)
    # super-block (J, J-1) couples steps (2J, 2J+1) to (2J-2, 2J-1): [[A2[2J-2], A1[2J-1]], [0, A2[2J-1]]]
    a2e, a2o, a1o = A2[0::2], A2[1::2], A1[1::2]
    lower = torch.cat([torch.cat([a2e, a1o], -1), torch.cat([torch.zeros_like(a2o), a2o], -1)], -2)
    return diag, lower


def _spd_inverse(blocks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Explicit inverses of small SPD blocks [n, L, b, b] and a [n, L] flag that is True where not PD.

    Explicit inverses turn every later solve into one batched matmul, which for blocks of a few rows is far
    cheaper than per-matrix LAPACK solves; the refinement step in `cyclic_solve` absorbs the extra rounding.
    """
    chol, info = torch.linalg.cholesky_ex(blocks)
    return torch.cholesky_inverse(chol), info > 0


def cyclic_factor(
    A0: torch.Tensor,  # [T, L, B, B] diagonal blocks (symmetric)
    A1: torch.Tensor,  # [T-1, L, B, B] sub-diagonal blocks (t+1, t)
    A2: torch.Tensor | None = None,  # [T-2, L, B, B] second sub-diagonal blocks (t+2, t), central rows only
) -> tuple[CyclicFactors, torch.Tensor]:
    """Factorise a block-tridiagonal (or -pentadiagonal) SPD matrix by block cyclic reduction.

    Args:
        A0: diagonal blocks.
        A1: first sub-diagonal blocks.
        A2: second sub-diagonal blocks, or None for a block-tridiagonal matrix.

    Returns:
        The factors and `bad`, a [L] bool tensor that is True for every left-hand side whose matrix was found
        not positive definite (a Cholesky of some reduced block failed). The caller decides how to report it.
    """
    paired = A2 is not None
    diag, lower = _pair_pentadiagonal(A0, A1, A2) if paired else (A0, A1)
    zero = _zero_block(diag)
    # low[i] = block (i, i-1) with explicit zero blocks at both ends, so every index below is in range
    low = torch.cat([zero, lower, zero])
    bad = torch.zeros(diag.shape[1], dtype=torch.bool, device=diag.device)
    levels = []
    while diag.shape[0] > 1:
        n = diag.shape[0]
        n_even = (n + 1) // 2
        dinv, fail = _spd_inverse(diag[1::2])
        bad |= fail.any(0)
        p, nx = dinv @ low[1:n:2], dinv @ low[2::2].mT  # P_i and N_i of every odd block
        levels.append(Level(dinv, p, nx))
        next_of_prev = torch.cat([zero, nx])[:n_even]  # N_{j−1} for even j (zero for j = 0)
        prev_of_next = torch.cat([p, zero])[:n_even]  # P_{j+1} for even j (zero past the end)
        low_even, low_after = low[0:n:2], low[1::2]  # blocks (j, j-1) and (j+1, j) for even j
        # Schur complement onto the even blocks: D'_j = D_j − L_j N_{j−1} − L_{j+1}ᵀ P_{j+1}
        diag = diag[0::2] - low_even @ next_of_prev - low_after.mT @ prev_of_next
        # new coupling (j, j−2) = −L_j P_{j−1}; row 0 stays zero because low[0] = 0
        low = torch.cat([-(low_even @ torch.cat([zero, p])[:n_even]), zero])
    root_inv, fail = _spd_inverse(diag)
    bad |= fail.any(0)
    return CyclicFactors(levels, root_inv, paired, (A0, A1, A2)), bad


def block_matvec(
    blocks: tuple[torch.Tensor, torch.Tensor, torch.Tensor | None],  # (A0, A1, A2) as in `cyclic_factor`
    x: torch.Tensor,  # [T, L, B, R]
) -> torch.Tensor:  # [T, L, B, R]
    """M x for the symmetric block-banded M given by its lower blocks."""
    a0, a1, a2 = blocks
    y = a0 @ x
    for lag, blk in ((1, a1), (2, a2)):
        if blk is not None and x.shape[0] > lag:
            _sub_matmul(y[lag:], blk, x[:-lag], alpha=1.0)
            _sub_matmul(y[:-lag], blk.mT, x[lag:], alpha=1.0)
    return y


def _sub_matmul(
    out: torch.Tensor,  # [n, L, p, R]
    a: torch.Tensor,  # [n, L, p, q]
    b: torch.Tensor,  # [n, L, q, R]
    alpha: float = -1.0,
) -> None:
    """out += alpha · a @ b in place for [n, L, ., .] tensors (each viewable as a batch of n·L matrices)."""
    if out.shape[0]:
        out.flatten(0, 1).baddbmm_(a.flatten(0, 1), b.flatten(0, 1), alpha=alpha)


def cyclic_solve(
    fac: CyclicFactors,
    rhs: torch.Tensor,  # [T, L, B, R] right-hand sides
    refine: int = 1,
) -> torch.Tensor:  # [T, L, B, R]
    """Solve with the factors of `cyclic_factor` (all R columns at once, O(log T) sequential levels).

    Cyclic reduction is backward stable for SPD matrices but, on the ill-conditioned S-MNN systems
    (cond ~ 1/h^{2K}), its forward error is about 100x that of the sequential sweep (1e-9 vs 1e-11 relative on
    a growing exponential over 1000 steps). One step of iterative refinement, x += M⁻¹(β − Mx), costs one
    block matvec and one more sweep and brings it back to the sequential solver's accuracy.

    Args:
        fac: the factors.
        rhs: right-hand sides.
        refine: number of iterative-refinement steps.

    Returns:
        The solution, same shape as `rhs`.
    """
    rhs = rhs.contiguous()
    x = _sweep(fac, rhs)
    for _ in range(refine):
        x += _sweep(fac, rhs - block_matvec(fac.blocks, x))
    return x


def _sweep(fac: CyclicFactors, rhs: torch.Tensor) -> torch.Tensor:
    """One reduction + back-substitution pass over the levels."""
    T = rhs.shape[0]
    b = rhs
    if fac.paired:  # [T, L, B, R] -> [T'/2, L, 2B, R]: super-block J stacks steps 2J and 2J+1
        if T % 2:
            b = torch.cat([b, _zero_block(b)])
        b = b.reshape(b.shape[0] // 2, 2, *b.shape[1:]).movedim(1, -3).flatten(-3, -2).contiguous()
    odd_rhs = []
    for lv in fac.levels:
        n_even, n_odd = (b.shape[0] + 1) // 2, b.shape[0] // 2
        b_odd = b[1::2].contiguous()  # only read from here on
        b = b[0::2].clone(memory_format=torch.contiguous_format)  # updated in place: never a view of rhs
        # b'_j = b_j − N_{j−1}ᵀ b_{j−1} − P_{j+1}ᵀ b_{j+1}: odd block m feeds even m (via P), m+1 (via N)
        _sub_matmul(b[:n_odd], lv.prev.mT, b_odd)
        k = min(n_odd, n_even - 1)
        _sub_matmul(b[1 : 1 + k], lv.next[:k].mT, b_odd[:k])
        odd_rhs.append(b_odd)
    x = fac.root_inv @ b
    for lv, b_odd in zip(fac.levels[::-1], odd_rhs[::-1], strict=True):
        n_even, n_odd = x.shape[0], b_odd.shape[0]
        # x_i = D_i⁻¹ b_i − P_i x_{i−1} − N_i x_{i+1} for odd i (x_{i+1} is zero past the end)
        x_odd = lv.dinv @ b_odd
        _sub_matmul(x_odd, lv.prev, x[:n_odd])
        k = min(n_odd, n_even - 1)
        _sub_matmul(x_odd[:k], lv.next[:k], x[1 : 1 + k])
        merged = x.new_empty((n_even + n_odd, *x.shape[1:]))
        merged[0::2] = x
        merged[1::2] = x_odd
        x = merged
    if fac.paired:
        x = x.unflatten(-2, (2, -1)).movedim(-3, 1).flatten(0, 1)
    return x[:T]
