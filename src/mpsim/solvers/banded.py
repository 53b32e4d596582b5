"""The sequential block-banded solver of the S-MNN normal equations (paper Alg. 2 and 4): a blocked Cholesky
sweep over time converted to LDLᵀ, and the forward/backward substitution with its factors.

Shared by `smnn.py` (the "banded" backend) and `smnn_cyclic.py` (which sweeps every chunk's interior with it).
Layout as in `smnn.py`: blocks are [T, L, B, B] with L independent left-hand sides, right-hand sides [T, L, B, R].
"""

from __future__ import annotations

from typing import NamedTuple

import torch


class BandedFactors(NamedTuple):
    """LDLᵀ factors as per-step lists of [L, B, B] views (split once: unbinding costs ~5 µs a step)."""

    dinv: list[torch.Tensor]  # T x [L, B, B] inverses of the LDLᵀ diagonal blocks D_t
    low1: list[torch.Tensor]  # T-1 x [L, B, B] unit-lower blocks L̃ (t+1, t) of the LDLᵀ factor
    low1_t: list[torch.Tensor]  # their transposes
    low2: list[torch.Tensor] | None  # T-2 x [L, B, B] unit-lower blocks (t+2, t), central rows only
    low2_t: list[torch.Tensor] | None


def banded_factor(
    a0: torch.Tensor,  # [T, L, B, B]
    a1: torch.Tensor,  # [T-1, L, B, B]
    a2: torch.Tensor | None = None,  # [T-2, L, B, B]
) -> tuple[BandedFactors, torch.Tensor]:
    """Blocked Cholesky sweep over time, then batched conversion to LDLᵀ; returns factors, [L] bad flags."""
    T = a0.shape[0]
    d0, d1 = a0.unbind(0), a1.unbind(0)
    d2 = None if a2 is None else a2.unbind(0)
    tri = torch.linalg.solve_triangular
    chol: list[torch.Tensor] = []
    low1: list[torch.Tensor] = []
    low2: list[torch.Tensor] = []
    infos: list[torch.Tensor] = []
    for s in range(T):  # the inherent sequential dependency (see smnn_cyclic.py for the parallel variant)
        diag = d0[s]
        if s >= 1:
            sub = d1[s - 1]
            if d2 is not None and s >= 2:
                l2 = tri(chol[s - 2].mT, d2[s - 2], upper=True, left=False)  # L_{s,s-2}
                low2.append(l2)
                sub = torch.baddbmm(sub, l2, low1[s - 2].mT, alpha=-1.0)
                diag = torch.baddbmm(diag, l2, l2.mT, alpha=-1.0)
            l1 = tri(chol[s - 1].mT, sub, upper=True, left=False)  # L_{s,s-1}
            low1.append(l1)
            diag = torch.baddbmm(diag, l1, l1.mT, alpha=-1.0)
        factor, info = torch.linalg.cholesky_ex(diag)
        chol.append(factor)
        infos.append(info)
    chol_t = torch.stack(chol)
    # LDLᵀ moves every triangular solve out of the substitution loops: L̃_{t+1,t} = L_{t+1,t} L_t⁻¹, and the
    # diagonal solve becomes a matmul with D_t⁻¹ (cheaper than per-block LAPACK solves for small B)
    ldl1 = tri(chol_t[:-1], torch.stack(low1), upper=False, left=False) if T > 1 else a1.clone()
    ldl2 = None
    if a2 is not None:
        ldl2 = tri(chol_t[:-2], torch.stack(low2), upper=False, left=False) if T > 2 else a2.clone()
    split = lambda m: None if m is None else list(m.unbind(0))  # noqa: E731
    fac = BandedFactors(
        list(torch.cholesky_inverse(chol_t).unbind(0)),
        list(ldl1.unbind(0)),
        list(ldl1.mT.unbind(0)),
        split(ldl2),
        split(None if ldl2 is None else ldl2.mT),
    )
    return fac, (torch.stack(infos) > 0).any(0)


def banded_solve(
    fac: BandedFactors,
    rhs: torch.Tensor,  # [T, L, B, R]
) -> torch.Tensor:  # [T, L, B, R]
    """Forward substitution with L̃, then backward substitution fused with the diagonal solve by D⁻¹.

    Each step reads and writes one [L, B, R] slab, in place in a single output buffer: the right-hand sides
    can be large (Lorenz: R = 512 columns), so the solve is bound by memory traffic, and keeping the diagonal
    solve inside the sweep (where the slab is still in cache) saves passes over them.
    """
    T = rhs.shape[0]
    b = rhs.unbind(0)
    x = torch.empty(rhs.shape, dtype=rhs.dtype, device=rhs.device)
    xs = x.unbind(0)
    xs[0].copy_(b[0])
    for s in range(1, T):  # z_s = b_s − L̃_{s,s−1} z_{s−1} (− L̃_{s,s−2} z_{s−2})
        torch.baddbmm(b[s], fac.low1[s - 1], xs[s - 1], alpha=-1.0, out=xs[s])
        if fac.low2 is not None and s >= 2:
            xs[s].baddbmm_(fac.low2[s - 2], xs[s - 2], alpha=-1.0)
    xs[T - 1].copy_(fac.dinv[T - 1] @ xs[T - 1])
    for s in range(T - 2, -1, -1):  # x_s = D_s⁻¹ z_s − L̃_{s+1,s}ᵀ x_{s+1} (− L̃_{s+2,s}ᵀ x_{s+2})
        torch.baddbmm(torch.bmm(fac.dinv[s], xs[s]), fac.low1_t[s], xs[s + 1], alpha=-1.0, out=xs[s])
        if fac.low2_t is not None and s <= T - 3:
            xs[s].baddbmm_(fac.low2_t[s], xs[s + 2], alpha=-1.0)
    return x
