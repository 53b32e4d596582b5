"""The S-MNN solver's data layout: independent left-hand sides L, right-hand-side columns R.

A batch of S-MNN problems whose left-hand side is broadcast along some batch dims (a constant-coefficient
layer shared by every window) is solved as L distinct matrices, each with R right-hand-side columns: those
batch dims move into the last (column) dim, so each matrix is factorised once and all its right-hand sides are
solved by one matmul per step. These helpers move tensors between the caller's batch-first layout and that
one, with transposes that run at memory speed (`permuted_copy`).
"""

from __future__ import annotations

import math

import torch


def permuted_copy(
    x: torch.Tensor,  # any dense tensor (a permutation of a contiguous one)
    perm: list[int],
) -> torch.Tensor:  # contiguous x.permute(perm)
    """`x.permute(perm).contiguous()` done as the lowest-rank transpose that expresses it.

    Moving a [T, 1, B, R] solution to [R, T, B] is a 2-D transpose of a [T·B, R] matrix, but a 4-D
    `permute().contiguous()` does not see that and runs 3-4x slower than memory speed (T = 5000, R = 1536:
    0.5 s against 0.14 s). Size-1 dims are dropped and dims that stay neighbours in memory are merged first.
    """
    out_shape = [x.shape[p] for p in perm]
    phys = sorted((d for d in range(x.dim()) if x.shape[d] != 1), key=lambda d: -x.stride()[d])  # memory order
    stride = 1
    for d in reversed(phys):
        if x.stride(d) != stride:  # overlapping or gapped (e.g. broadcast): nothing to merge safely
            return x.permute(perm).contiguous()
        stride *= x.shape[d]
    pos = {d: i for i, d in enumerate(phys)}
    groups: list[list[int]] = []
    for d in (p for p in perm if x.shape[p] != 1):  # output order; neighbours in memory merge
        if groups and pos[d] == pos[groups[-1][-1]] + 1:
            groups[-1].append(d)
        else:
            groups.append([d])
    sizes = [math.prod(x.shape[d] for d in g) for g in groups]
    in_memory = sorted(range(len(groups)), key=lambda g: pos[groups[g][0]])
    phys_sizes = [sizes[g] for g in in_memory]
    strides = [math.prod(phys_sizes[i + 1 :]) for i in range(len(phys_sizes))]
    src = x.as_strided(phys_sizes, strides, x.storage_offset())
    out = x.new_empty(sizes)
    out.copy_(src.permute([in_memory.index(g) for g in range(len(groups))]))
    return out.view(out_shape)


class PermutedCopy(torch.autograd.Function):
    """Differentiable `permuted_copy` (the gradient goes back through the inverse permutation, also fast)."""

    @staticmethod
    def forward(ctx, x, perm):  # x: any dense tensor, perm: list of dims
        ctx.inverse = sorted(range(len(perm)), key=perm.__getitem__)
        return permuted_copy(x, perm)

    @staticmethod
    def backward(ctx, grad):
        return permuted_copy(grad, ctx.inverse), None


def batch_to_columns(
    x: torch.Tensor,  # [T', *batch, X]
    batch_lhs: torch.Size,
    batch: torch.Size,
) -> torch.Tensor:  # [T', L, X, R]
    """Move the batch dims along which the left-hand side is broadcast (size 1 in batch_lhs) into R columns.

    Each distinct matrix (L of them) is then factorised once, and all its right-hand sides are solved by one
    matmul per step instead of a batched matmul per right-hand side.
    """
    x = x.expand(x.shape[0], *batch, x.shape[-1])
    return PermutedCopy.apply(x, _column_perm(batch_lhs)).reshape(x.shape[0], math.prod(batch_lhs), x.shape[-1], -1)


def columns_to_batch(
    x: torch.Tensor,  # [T', L, X, R]
    batch_lhs: torch.Size,
    batch: torch.Size,
) -> torch.Tensor:  # [T', *batch, X]
    """Inverse of `batch_to_columns` (a view)."""
    perm = _column_perm(batch_lhs)
    full = (x.shape[0], *batch, x.shape[2])
    x = x.reshape([full[p] for p in perm])
    return x.permute(sorted(range(len(perm)), key=perm.__getitem__))


def columns_to_output(
    x: torch.Tensor,  # [T, L, X, R]
    batch_lhs: torch.Size,
    batch: torch.Size,
    copy: bool = False,
) -> torch.Tensor:  # [*batch, T, X]
    """The solver's result in the caller's batch-first layout: a permuted view of `x` (no pass over the
    solution, which at T = 5000 and 1536 columns is 184 MB), or with `copy` a contiguous copy made in one fast
    transpose (see `permuted_copy`)."""
    perm = _column_perm(batch_lhs)  # dim k of the reshaped x holds axis perm[k] of (T, *batch, X)
    full = (x.shape[0], *batch, x.shape[2])
    x = x.reshape([full[p] for p in perm])
    order = [perm.index(a) for a in [*range(1, len(batch) + 1), 0, len(batch) + 1]]  # (*batch, T, X)
    return PermutedCopy.apply(x, order) if copy else x.permute(order)


def _column_perm(batch_lhs: torch.Size) -> list[int]:
    lhs_axes = [1 + i for i, n in enumerate(batch_lhs) if n != 1]
    rhs_axes = [1 + i for i, n in enumerate(batch_lhs) if n == 1]
    return [0, *lhs_axes, len(batch_lhs) + 1, *rhs_axes]
