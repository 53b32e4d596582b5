"""Parallel-in-time solves of the S-MNN normal equations: chunked block cyclic reduction.

The banded LDLᵀ of `mpsim.solvers.banded` walks the T time blocks one after another, so its cost is T times the
launch overhead of a few tiny kernels. Block cyclic reduction removes the odd-numbered time blocks by a Schur
complement, which leaves a block-tridiagonal SPD system on the even blocks of half the length; repeating this
⌈log₂ T⌉ times leaves one block. Every level is a handful of batched operations over all its blocks, so the
sequential depth is O(log T) and the work O(T·B³). For an SPD matrix this is Cholesky on a permutation of the
unknowns, hence backward stable.

Pure cyclic reduction moves the right-hand sides through memory at every level (about 13 passes over them per
solve, plus a refinement solve for accuracy), and with many right-hand sides (Lorenz: 1536 columns) the solve is
bound by that traffic. So long sequences are first cut into chunks of `chunk` interior blocks separated by
single separator blocks. The chunk interiors are independent once the separators are known: they are factorised
and swept by the sequential LDLᵀ of `banded.py`, vectorised over all chunks at once (depth `chunk`), their
couplings to the two neighbouring separators ("spikes") are solved once per left-hand side, and the Schur
complement on the separators — block-tridiagonal, 1/(chunk+1) of the size — is solved by cyclic reduction.
A solve then reads the right-hand sides about five times, and the sequential depth is O(chunk + log T).

The block-pentadiagonal system of central smoothness rows is handled by pairing time steps (t = 2J, 2J+1)
into super-blocks of size 2B, which makes it block-tridiagonal again.

Layout (as in `smnn.py`): blocks are [T, L, B, B] with L independent left-hand sides (the flattened batch of
left-hand sides) and right-hand sides are [T, L, B, R] with R columns sharing each left-hand side. `A1[t]` is
the block (t+1, t) and `A2[t]` the block (t+2, t); only lower blocks are passed, the matrix is symmetric.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from mpsim.solvers.banded import BandedFactors, banded_factor

#: interior blocks per chunk: long enough that a solve reads the right-hand sides ~5 times (pure cyclic
#: reduction: ~13), short enough that the sequential part (2·CHUNK small steps) stays a few hundred kernels
CHUNK = 16
#: on a CPU, the data of one sweep step over all chunks should fit in the per-core L2 cache
SLAB_BYTES = 1 << 20


class Level(NamedTuple):
    """One reduction level: its odd blocks i = 2m+1 are x_i = D_i⁻¹ b_i − P_i x_{i−1} − N_i x_{i+1}."""

    dinv: torch.Tensor  # [n_odd, L, b, b] D_i⁻¹
    prev: torch.Tensor  # [n_odd, L, b, b] P_i = D_i⁻¹ · block (i, i−1)
    next: torch.Tensor  # [n_odd, L, b, b] N_i = D_i⁻¹ · block (i, i+1) (zero past the end)


class Reduction(NamedTuple):
    """Pure block cyclic reduction of a block-tridiagonal matrix."""

    levels: list[Level]  # finest first
    root_inv: torch.Tensor  # [1, L, b, b] inverse of the last remaining block
    blocks: tuple[torch.Tensor, torch.Tensor]  # (diagonal [n, L, b, b], sub-diagonal [n-1, L, b, b])


class ChunkSet(NamedTuple):
    """Q chunks of m interior blocks, eliminated by the sequential LDLᵀ vectorised over the chunks.

    With the chunk's LDLᵀ factor L̃DL̃ᵀ and its couplings E_l (first block to the separator on its left) and
    E_r (last block to the separator on its right), e = L̃⁻¹[E_l | E_r] are the forward-substituted spikes.
    """

    inner: BandedFactors  # LDLᵀ of every chunk: m steps of [Q·L, b, b]
    h: list[torch.Tensor]  # m x [Q·L, b, b] e_l[j]ᵀ D_j⁻¹: how step j enters the left separator's equation
    g: list[torch.Tensor]  # m x [Q·L, b, 2b or b] D_j⁻¹ e[j]: how the separators enter step j
    k: torch.Tensor | None  # [Q·L, b, b] E_rᵀ D_{m−1}⁻¹: how the last step enters the right separator's


class Chunked(NamedTuple):
    """Chunks of m interior blocks, each followed by a separator block, then a tail of r < m+1 blocks.

    Block p·(m+1) + j is interior block j of chunk p for j < m and separator p for j = m; the last n − P(m+1)
    blocks are the tail, a chunk without a right separator. The separators' Schur complement is again
    block-tridiagonal and is solved by cyclic reduction.
    """

    main: ChunkSet  # the P full chunks
    tail: ChunkSet | None  # the last r blocks (None when n is a multiple of m+1)
    separators: Reduction  # the Schur complement on the P separators
    m: int  # interior blocks per chunk


class CyclicFactors(NamedTuple):
    core: Reduction | Chunked
    paired: bool  # time steps were paired into 2B super-blocks (central rows)


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
    cheaper than per-matrix LAPACK solves; the refinement step in `_reduce_solve` absorbs the extra rounding.
    """
    chol, info = torch.linalg.cholesky_ex(blocks)
    return torch.cholesky_inverse(chol), info > 0


def _reduce_factor(
    diag: torch.Tensor,  # [n, L, b, b] diagonal blocks
    lower: torch.Tensor,  # [n-1, L, b, b] sub-diagonal blocks (i+1, i)
) -> tuple[Reduction, torch.Tensor]:  # factors, [L] not-positive-definite flags
    """Block cyclic reduction of a block-tridiagonal SPD matrix (⌈log₂ n⌉ levels)."""
    blocks = (diag, lower)
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
    return Reduction(levels, root_inv, blocks), bad


def _reduce_sweep(red: Reduction, b: torch.Tensor) -> torch.Tensor:  # b: [n, L, b, R] -> [n, L, b, R]
    """One reduction + back-substitution pass over the levels."""
    odd_rhs = []
    for lv in red.levels:
        n_even, n_odd = (b.shape[0] + 1) // 2, b.shape[0] // 2
        b_odd = b[1::2].contiguous()  # only read from here on
        b = b[0::2].clone(memory_format=torch.contiguous_format)  # updated in place: never a view of rhs
        # b'_j = b_j − N_{j−1}ᵀ b_{j−1} − P_{j+1}ᵀ b_{j+1}: odd block m feeds even m (via P), m+1 (via N)
        _sub_matmul(b[:n_odd], lv.prev.mT, b_odd)
        k = min(n_odd, n_even - 1)
        _sub_matmul(b[1 : 1 + k], lv.next[:k].mT, b_odd[:k])
        odd_rhs.append(b_odd)
    x = red.root_inv @ b
    for lv, b_odd in zip(red.levels[::-1], odd_rhs[::-1], strict=True):
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
    return x


def _reduce_solve(red: Reduction, b: torch.Tensor, refine: int) -> torch.Tensor:  # b: [n, L, b, R]
    """Cyclic-reduction solve with `refine` steps of iterative refinement, x += M⁻¹(b − Mx).

    Cyclic reduction is backward stable for SPD matrices but, on the ill-conditioned S-MNN systems
    (cond ~ 1/h^{2K}), its forward error is about 100x that of the sequential sweep (1e-9 vs 1e-11 relative on
    a growing exponential over 1000 steps); one refinement step brings it back to the sweep's accuracy.
    """
    x = _reduce_sweep(red, b)
    for _ in range(refine):
        x += _reduce_sweep(red, b - block_matvec((*red.blocks, None), x))
    return x


def chunk_length(n_blocks: int, step_bytes: int, device: torch.device) -> int:
    """Interior blocks per chunk: `CHUNK`, or more on a CPU when a time step carries a lot of data.

    Each sweep step touches one slab of every chunk. On a CPU the slabs of all P chunks should stay in cache
    (≤ `SLAB_BYTES`), so with wide right-hand sides (Lorenz: 1536 columns, 37 KB a step) the chunks grow and
    P shrinks; the sequential depth is then ~2n/P instead of O(log n). On a GPU the chunks stay short.
    """
    if device.type != "cpu":
        return CHUNK
    n_chunks = max(2, SLAB_BYTES // max(step_bytes, 1))
    return max(CHUNK, -(-n_blocks // n_chunks))


def _chunk_set(
    diag: torch.Tensor,  # [m, Q·L, b, b] interior diagonal blocks, step-major
    lower: torch.Tensor,  # [m−1, Q·L, b, b] interior sub-diagonal blocks
    left: torch.Tensor,  # [Q·L, b, b] coupling of the first block to the left separator (zero if none)
    right: torch.Tensor | None,  # [Q·L, b, b] block (right separator, last block); None: no right separator
) -> tuple[ChunkSet, torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """Factor the chunks and their separator couplings.

    Returns:
        The set; [Q·L] not-positive-definite flags; its Schur terms E_lᵀM⁻¹E_l (on the left separator),
        E_rᵀM⁻¹E_r (on the right one) and E_rᵀM⁻¹E_l (between them), the last two None without a right one.
    """
    m = diag.shape[0]
    inner, bad = banded_factor(diag, lower)
    e = [left]
    for j in range(1, m):  # forward substitution of the spike: only the first block is coupled
        e.append(-(inner.low1[j - 1] @ e[-1]))
    h = [ej.mT @ dj for ej, dj in zip(e, inner.dinv, strict=True)]
    q_left = h[0] @ e[0]  # m ≥ 1 blocks
    for hj, ej in zip(h[1:], e[1:], strict=True):
        q_left = q_left + hj @ ej
    if right is None:
        return (
            ChunkSet(inner, h, [dj @ ej for dj, ej in zip(inner.dinv, e, strict=True)], None),
            bad,
            q_left,
            None,
            None,
        )
    zero = torch.zeros_like(right)
    g = [
        dj @ torch.cat([ej, right.mT if j == m - 1 else zero], -1)
        for j, (dj, ej) in enumerate(zip(inner.dinv, e, strict=True))
    ]
    k = right @ inner.dinv[-1]
    return ChunkSet(inner, h, g, k), bad, q_left, k @ right.mT, k @ e[-1]


def _chunked_factor(
    diag: torch.Tensor,  # [n, L, b, b] diagonal blocks
    lower: torch.Tensor,  # [n-1, L, b, b] sub-diagonal blocks (i+1, i)
    m: int,  # interior blocks per chunk
) -> tuple[Chunked, torch.Tensor]:  # factors, [L] not-positive-definite flags
    """Eliminate the chunk interiors (sequential LDLᵀ, vectorised over chunks), then reduce the separators."""
    n, L, b = diag.shape[0], diag.shape[1], diag.shape[-1]
    P = n // (m + 1)
    full = P * (m + 1)
    low = torch.cat([lower, _zero_block(diag)])  # low[i] = block (i+1, i), zero past the end
    d5, l5 = diag[:full].view(P, m + 1, L, b, b), low[:full].view(P, m + 1, L, b, b)
    to_sep, from_sep = l5[:, m - 1], l5[:, m]  # blocks (sep p, last of chunk p), (first after sep p, sep p)
    left = torch.cat([_zero_block(from_sep), from_sep[:-1]])  # chunk 0 has no separator on its left
    main, bad_main, q_left, s_right, s_cross = _chunk_set(
        d5[:, :m].transpose(0, 1).reshape(m, P * L, b, b),
        l5[:, : m - 1].transpose(0, 1).reshape(m - 1, P * L, b, b),
        left.reshape(P * L, b, b),
        to_sep.reshape(P * L, b, b),
    )
    assert s_right is not None and s_cross is not None  # given a right separator
    q_left = q_left.view(P, L, b, b)
    # Schur complement on the separators: S_pp = D_p − E_rᵀM⁻¹E_r (chunk p) − E_lᵀM⁻¹E_l (chunk p+1 or tail)
    from_next = torch.cat([q_left[1:], _zero_block(q_left)])
    tail, bad = None, bad_main.view(P, L).any(0)
    if n > full:
        tail, bad_tail, q_tail, _, _ = _chunk_set(diag[full:], lower[full:], from_sep[-1], None)
        from_next = torch.cat([q_left[1:], q_tail[None]])
        bad = bad | bad_tail
    s_diag = d5[:, m] - s_right.view(P, L, b, b) - from_next
    s_low = -s_cross.view(P, L, b, b)[1:]  # S_{p,p−1} = −E_rᵀM_p⁻¹E_l through chunk p
    separators, bad_sep = _reduce_factor(s_diag, s_low)
    return Chunked(main, tail, separators, m), bad | bad_sep


def _forward(cs: ChunkSet, ins: list[torch.Tensor], outs: list[torch.Tensor]) -> torch.Tensor:
    """z = L̃⁻¹ b into `outs` (slabs [Q·L, b, R]); returns Σ_j h_j z_j, the chunk's pull on its left separator."""
    outs[0].copy_(ins[0])
    acc = cs.h[0] @ outs[0]
    for j in range(1, len(ins)):
        torch.baddbmm(ins[j], cs.inner.low1[j - 1], outs[j - 1], alpha=-1.0, out=outs[j])
        acc.baddbmm_(cs.h[j], outs[j])
    return acc


def _backward(cs: ChunkSet, outs: list[torch.Tensor], seps: torch.Tensor) -> None:
    """x_j = D_j⁻¹ z_j − g_j (y_left; y_right) − L̃ᵀ x_{j+1}, in place in `outs` (seps: [Q·L, 2b or b, R])."""
    m = len(outs)
    for j in range(m - 1, -1, -1):
        torch.baddbmm(cs.inner.dinv[j] @ outs[j], cs.g[j], seps, alpha=-1.0, out=outs[j])
        if j < m - 1:
            outs[j].baddbmm_(cs.inner.low1_t[j], outs[j + 1], alpha=-1.0)


def _chunked_solve(ch: Chunked, rhs: torch.Tensor, refine: int) -> torch.Tensor:  # rhs: [n, L, b, R]
    """Forward sweeps of all chunks, the separator solve, backward sweeps with the separators folded in.

    The right-hand sides are read once and the solution written once per sweep (two passes, like the sequential
    sweep), and the chunks' slabs are views into the input and output, so nothing is gathered or scattered.
    """
    n, L, b, R = rhs.shape
    m = ch.m
    P = ch.main.g[0].shape[0] // L
    full = P * (m + 1)
    x = torch.empty_like(rhs, memory_format=torch.contiguous_format)
    r5, x5 = rhs[:full].view(P, m + 1, L, b, R), x[:full].view(P, m + 1, L, b, R)
    if L == 1:  # slab j of every chunk is a strided view [P, b, R]
        ins, outs = list(r5[:, :, 0].unbind(1)), list(x5[:, :, 0].unbind(1))
        work = None
    else:  # chunk and left-hand-side dims do not merge in a view: work step-major, copy back at the end
        work = r5.transpose(0, 1).reshape(m + 1, P * L, b, R)
        ins = outs = list(work.unbind(0))
    acc = _forward(ch.main, ins[:m], outs[:m]).view(P, L, b, R)
    # separator equations with the interiors eliminated: g_p = b_p − E_rᵀ D⁻¹ z_last(p) − Σ_j h_j z_j(p+1)
    assert ch.main.k is not None  # the full chunks always have a right separator
    g = ins[m].reshape(P, L, b, R) - (ch.main.k @ outs[m - 1]).view(P, L, b, R)
    pulls = [acc[1:]]
    if ch.tail is not None:
        t_ins, t_outs = list(rhs[full:].unbind(0)), list(x[full:].unbind(0))
        pulls.append(_forward(ch.tail, t_ins, t_outs)[None])
    else:
        pulls.append(_zero_block(acc))
    g = g - torch.cat(pulls)
    y = _reduce_solve(ch.separators, g, refine)  # [P, L, b, R]
    outs[m].copy_(y.reshape(outs[m].shape))
    seps = torch.cat([torch.cat([_zero_block(y), y[:-1]]), y], -2).view(P * L, 2 * b, R)  # (y_{p−1}; y_p)
    _backward(ch.main, outs[:m], seps)
    if ch.tail is not None:
        _backward(ch.tail, t_outs, y[-1])
    if work is not None:
        x5.copy_(work.view(m + 1, P, L, b, R).transpose(0, 1))
    return x


def cyclic_factor(
    A0: torch.Tensor,  # [T, L, B, B] diagonal blocks (symmetric)
    A1: torch.Tensor,  # [T-1, L, B, B] sub-diagonal blocks (t+1, t)
    A2: torch.Tensor | None = None,  # [T-2, L, B, B] second sub-diagonal blocks (t+2, t), central rows only
    chunk: int | None = None,
    width: int = 1,
) -> tuple[CyclicFactors, torch.Tensor]:
    """Factorise a block-tridiagonal (or -pentadiagonal) SPD matrix for parallel-in-time solves.

    Args:
        A0: diagonal blocks.
        A1: first sub-diagonal blocks.
        A2: second sub-diagonal blocks, or None for a block-tridiagonal matrix.
        chunk: interior blocks per chunk (None: `chunk_length`); sequences shorter than two chunks use pure
            cyclic reduction.
        width: right-hand-side columns R the factors will be used with (sets the default chunk length).

    Returns:
        The factors and `bad`, a [L] bool tensor that is True for every left-hand side whose matrix was found
        not positive definite (a Cholesky of some reduced block failed). The caller decides how to report it.
    """
    paired = A2 is not None
    diag, lower = (A0, A1) if A2 is None else _pair_pentadiagonal(A0, A1, A2)
    if chunk is None:
        chunk = chunk_length(diag.shape[0], diag.shape[1] * diag.shape[-1] * width * diag.element_size(), diag.device)
    core: Reduction | Chunked
    if chunk >= 2 and diag.shape[0] >= 2 * (chunk + 1):
        core, bad = _chunked_factor(diag, lower, chunk)
    else:
        core, bad = _reduce_factor(diag, lower)
    return CyclicFactors(core, paired), bad


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
    """Solve with the factors of `cyclic_factor` (all R columns at once, O(chunk + log T) sequential depth).

    Args:
        fac: the factors.
        rhs: right-hand sides.
        refine: iterative-refinement steps of the cyclic-reduction solve (of the whole system for short
            sequences, of the separator system for chunked ones; see `_reduce_solve`).

    Returns:
        The solution, same shape as `rhs`.
    """
    T = rhs.shape[0]
    b = rhs.contiguous()
    if fac.paired:  # [T, L, B, R] -> [T'/2, L, 2B, R]: super-block J stacks steps 2J and 2J+1
        if T % 2:
            b = torch.cat([b, _zero_block(b)])
        b = b.reshape(b.shape[0] // 2, 2, *b.shape[1:]).movedim(1, -3).flatten(-3, -2).contiguous()
    if isinstance(fac.core, Chunked):
        x = _chunked_solve(fac.core, b, refine)
    else:
        x = _reduce_solve(fac.core, b, refine)
    if fac.paired:
        x = x.unflatten(-2, (2, -1)).movedim(-3, 1).flatten(0, 1)
    return x[:T]
