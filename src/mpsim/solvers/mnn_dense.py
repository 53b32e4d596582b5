"""Dense baselines with cubic cost in T: the S-MNN system solved densely, and the original MNN with a slack.

`dense_solve` scatters the S-MNN blocks into a full (T·B)×(T·B) matrix and uses a dense Cholesky: the same
answers as `smnn_solve` at O(T³B³) time and O(T²B²) memory (the cubic-vs-linear comparison of the paper).
`mnn_dense_solve` is the original MNN (mech-nn, spec §6.1): forward/backward Taylor rows up to order K-1 and
central rows for the top order, each with one shared slack unknown ε, unweighted least squares over [ε, u].
Both differentiate by autograd through `cholesky_ex`/`cholesky_solve`, which makes them independent gradient
oracles for the banded solver. Both estimate their memory before allocating and refuse beyond `max_bytes`.
"""

from __future__ import annotations

import math

import torch

from mpsim.solvers.smnn import (
    SMNNProblem,
    SolverError,
    assemble_blocks,
    check_determined,
    prepare_problem,
    taylor_matrix,
)
from mpsim.solvers.smnn_layout import batch_to_columns, columns_to_batch


class DenseSizeError(SolverError):
    """The dense matrix would not fit in `max_bytes`; raised before anything large is allocated.

    Attributes:
        need_bytes: the estimated memory of the dense solve.
        limit_bytes: the budget it exceeded.
    """

    def __init__(self, message: str, need_bytes: int = 0, limit_bytes: int = 0) -> None:
        super().__init__(message)
        self.need_bytes, self.limit_bytes = need_bytes, limit_bytes


def _memory_budget(device: torch.device) -> int:
    """Default `max_bytes`: half of MemAvailable on a CPU, 80% of the free memory on a GPU."""
    if device.type == "cuda":
        return int(0.8 * torch.cuda.mem_get_info(device)[0])
    try:
        with open("/proc/meminfo") as f:
            avail = next(int(line.split()[1]) * 1024 for line in f if line.startswith("MemAvailable"))
        return avail // 2
    except (OSError, StopIteration):
        return 8 * 2**30


def _guard_size(
    n_mats: int,
    rows: int,
    n: int,
    cols: int,
    dtype: torch.dtype,
    max_bytes: int | None,
    device: torch.device,
    what: str,
) -> None:
    """Refuse before allocating. Counts the dense n×n matrix, the block scatter, the factor, the refinement
    product and autograd's saved copies (8 n² per system: measured 7.1 n² at peak for 1536 per-sample
    150×150 systems with a backward pass), plus the constraint matrix of the MNN (2 m·n)."""
    item = torch.finfo(dtype).bits // 8
    need = n_mats * (8 * n * n + 2 * rows * n + 3 * n * cols) * item
    limit = _memory_budget(device) if max_bytes is None else max_bytes
    if need > limit:
        raise DenseSizeError(
            f"{what} needs about {need / 2**30:.2f} GiB ({n_mats} dense {n}x{n} systems, memory O(T²)) but "
            f"max_bytes is {limit / 2**30:.2f} GiB. Use smnn_solve(method='banded' or 'cyclic'), which is "
            "linear in T, or shorten the sequence / batch.",
            need,
            limit,
        )


def _dense_cholesky_solve(mat: torch.Tensor, rhs: torch.Tensor, what: str) -> torch.Tensor:
    """Cholesky solve of [L, n, n] SPD matrices with one step of iterative refinement ([L, n, R] -> same)."""
    chol, info = torch.linalg.cholesky_ex(mat)
    if bool((info > 0).any()):
        bad = int(torch.nonzero(info > 0)[0])
        raise SolverError(
            f"{what}: the normal matrix is not positive definite (system {bad}, pivot "
            f"{int(info.flatten()[bad])}). Check that the equation and initial-value rows "
            "determine the solution and that no input is NaN/inf."
        )
    x = torch.cholesky_solve(rhs, chol)
    # cond ~ 1/h^{2K}: one step of iterative refinement recovers the banded solver's accuracy
    return x + torch.cholesky_solve(rhs - mat @ x, chol)


def dense_solve(
    coefficients: torch.Tensor,  # [*batch, T or 1, E, D, O]
    rhs_equation: torch.Tensor,  # [*batch, T or 1, E]
    init_vars: torch.Tensor,  # [*batch, S or 1, D, I]
    steps: torch.Tensor | float,  # [*batch, T-1 or 1]
    *,
    n_steps: int | None = None,
    n_init_var_steps: int | None = None,
    weight_equation: float = 1.0,
    weight_init_var: float = 1.0,
    weight_smooth: float = 1.0,
    central: bool = False,
    step_dim_first: bool = False,
    check: bool = True,
    dtype: torch.dtype = torch.float64,
    max_bytes: int | None = None,
) -> torch.Tensor:  # [*batch, T, D, O]
    """The S-MNN system of `smnn_solve`, solved with a dense Cholesky of the full normal matrix.

    Args:
        coefficients, rhs_equation, init_vars, steps, n_steps, n_init_var_steps, weight_equation,
            weight_init_var, weight_smooth, central, step_dim_first, check, dtype: as in `smnn_solve`.
        max_bytes: memory budget for the dense matrices; None: half the free RAM (80% of free GPU memory).

    Returns:
        u[..., t, d, k], as `smnn_solve`.

    Raises:
        DenseSizeError: the dense matrices would exceed `max_bytes` (checked before allocating).
        SolverError: invalid inputs, a singular or non-positive-definite system.
    """
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
    T, (_, D, O) = prob.n_steps, prob.dims
    B, L, R = D * O, math.prod(prob.batch_lhs), math.prod(prob.batch) // math.prod(prob.batch_lhs)
    _guard_size(L, 0, T * B, R, dtype, max_bytes, prob.coefficients.device, "dense S-MNN solve")
    if check:
        check_determined(prob)
    a0, a1, a2, beta = assemble_blocks(prob)
    mat = a0.new_zeros(L, T, B, T, B)
    t = torch.arange(T, device=a0.device)
    mat[:, t, :, t, :] = a0  # indices separated by a slice put the time axis first: [T, L, B, B]
    for lag, blk in ((1, a1), (2, a2)):
        if blk is not None and T > lag:
            mat[:, t[lag:], :, t[:-lag], :] = blk
            mat[:, t[:-lag], :, t[lag:], :] = blk.mT
    rhs = beta.transpose(0, 1).reshape(L, T * B, -1)
    x = _dense_cholesky_solve(mat.reshape(L, T * B, T * B), rhs, "dense S-MNN solve")
    x = x.reshape(L, T, B, -1).transpose(0, 1)
    u = columns_to_batch(x, prob.batch_lhs, prob.batch).movedim(0, -2)
    return u.reshape(*prob.batch, T, D, O).to(out_dtype)


def _mnn_matrix(prob: SMNNProblem) -> torch.Tensor:
    """Dense MNN constraint matrix [*batch_lhs, m, 1 + T·B] over y = [ε, u] (rows: EQ, IV, FWD, CEN, BWD)."""
    T, S = prob.n_steps, prob.n_init_steps
    E, D, O = prob.dims
    B, K, I = D * O, O - 1, prob.init.shape[-1] if prob.n_init_steps > 0 else 0
    dt, dev = prob.coefficients.dtype, prob.coefficients.device
    bl = prob.batch_lhs
    t = torch.arange(T, device=dev)
    coef = prob.coefficients.expand(T, *bl, E, D, O).reshape(T, *bl, E, B)
    eq = coef.new_zeros(*bl, T, E, T, B)
    eq[..., t, :, t, :] = coef
    eq = eq.reshape(*bl, T * E, T * B)
    iv = torch.zeros(S, D, I, T, D, O, dtype=dt, device=dev)  # u_{s,d,k} = v_{s,d,k}
    s_, d_, k_ = torch.meshgrid(*(torch.arange(n, device=dev) for n in (S, D, I)), indexing="ij")
    iv[s_, d_, k_, s_, d_, k_] = 1.0
    iv = iv.reshape(S * D * I, T * B).expand(*bl, S * D * I, T * B)
    h = prob.steps.expand(T - 1, *prob.steps.shape[1:]).movedim(0, -1).expand(*bl, T - 1)  # [*bl, T-1]
    orders = torch.arange(O, device=dev)
    F = taylor_matrix(O, dt, dev)[:K]  # rows i = 0..K-1
    unit = torch.eye(O, dtype=dt, device=dev)[:K]
    # row (t, i) touches u_t (slot 0) and u_{t+1} (slot 1) of the same dim, plus ε
    hp = h[..., None, None]
    fwd = torch.stack([hp**orders * F, -(hp ** orders[:K, None]) * unit], -2)
    hn = -h[..., None, None]
    bwd = torch.stack([-(hn ** orders[:K, None]) * unit, hn**orders * F], -2)
    H = (h[..., :-1] + h[..., 1:])[..., None]  # [*bl, T-2, 1]
    top = torch.zeros(*H.shape[:-1], 3, O, dtype=dt, device=dev)  # slots u_t, u_{t+1}, u_{t+2}
    top[..., 0, K - 1] = -(H[..., 0] ** (K - 2))
    top[..., 1, K] = -(H[..., 0] ** (K - 1))
    top[..., 2, K - 1] = H[..., 0] ** (K - 2)
    rows = []
    for local, n_slots, n_rows in ((fwd, 2, K), (top[..., None, :, :], 3, 1), (bwd, 2, K)):
        n_t = T - n_slots + 1
        dense = local.new_zeros(*bl, n_t, D, n_rows, T, D, O)
        tt, dd = t[:n_t, None], torch.arange(D, device=dev)[None, :]
        for slot in range(n_slots):  # 2 or 3 slots, not a loop over data
            dense[..., tt, dd, :, tt + slot, dd, :] = local[..., slot, :].movedim(-3, 0)[:, None]
        rows.append(dense.reshape(*bl, n_t * D * n_rows, T * B))
    smooth = torch.cat(rows, -2)
    u_part = torch.cat([eq, iv, smooth], -2)
    slack = torch.cat(
        [u_part.new_zeros(*bl, eq.shape[-2] + iv.shape[-2], 1), u_part.new_ones(*bl, smooth.shape[-2], 1)], -2
    )
    return torch.cat([slack, u_part], -1)


def mnn_dense_solve(
    coefficients: torch.Tensor,  # [*batch, T or 1, E, D, O]
    rhs_equation: torch.Tensor,  # [*batch, T or 1, E]
    init_vars: torch.Tensor,  # [*batch, S or 1, D, I]
    steps: torch.Tensor | float,  # [*batch, T-1 or 1]
    *,
    n_steps: int | None = None,
    n_init_var_steps: int | None = None,
    gamma: float = 0.05,
    alpha: float = 0.0,
    step_dim_first: bool = False,
    dtype: torch.dtype = torch.float64,
    max_bytes: int | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:  # u [*batch, T, D, O], slack [*batch]
    """The original (dense) MNN solve with a slack unknown ε (mech-nn; spec §6.1).

    Rows: equations Σ c·u = r; initial values u_{s,d,k} = v (s < S, k < I); for every step pair and
    i = 0..K-1 the forward rows ε + Σ_j h^j/(j−i)! u_{t,j} − hⁱ u_{t+1,i} = 0 and backward rows (step −h);
    central rows ε − H^{K−2} u_{t−1,K−1} + H^{K−2} u_{t+1,K−1} − H^{K−1} u_{t,K} = 0 with H = h_{t−1} + h_t.
    Solves y = (MᵀM)⁻¹(Mᵀb + γα e₀); with the reference's α = 0 this is unweighted least squares over [ε, u].

    Args:
        coefficients, rhs_equation, init_vars, steps, n_steps, n_init_var_steps, step_dim_first, dtype: as in
            `smnn_solve` (steps are shared by all dims here).
        gamma: the QP's γ (only enters through γα).
        alpha: the QP's linear cost on ε.
        max_bytes: memory budget; None: half the free RAM (80% of free GPU memory).

    Returns:
        u[..., t, d, k] and the slack ε per batch element.

    Raises:
        DenseSizeError: the dense matrices would exceed `max_bytes` (checked before allocating).
        SolverError: invalid inputs (O < 2) or a non-positive-definite MᵀM.
    """
    if coefficients.shape[-1] < 2:
        raise SolverError(f"the MNN's central rows need n_orders ≥ 2; got {coefficients.shape[-1]}.")
    out_dtype = torch.promote_types(coefficients.dtype, rhs_equation.dtype)
    prob = prepare_problem(
        coefficients,
        rhs_equation,
        init_vars,
        steps,
        n_steps=n_steps,
        n_init_var_steps=n_init_var_steps,
        central=True,
        step_dim_first=step_dim_first,
        weights=(1.0, 1.0, 1.0),
        dtype=dtype,
    )
    T, S = prob.n_steps, prob.n_init_steps
    E, D, O = prob.dims
    B, n = D * O, 1 + T * D * O
    n_iv = prob.init.shape[-1] if S > 0 else 0
    L, R = math.prod(prob.batch_lhs), math.prod(prob.batch) // math.prod(prob.batch_lhs)
    m = T * E + S * D * n_iv + (2 * (O - 1) * (T - 1) + (T - 2)) * D
    _guard_size(L, m, n, R, dtype, max_bytes, prob.coefficients.device, "dense MNN solve")
    mat = _mnn_matrix(prob).reshape(L, m, n)
    rhs = batch_to_columns(prob.rhs.expand(T, *prob.rhs.shape[1:]), prob.batch_lhs, prob.batch)
    init = prob.init[..., :n_iv].expand(S, *prob.init.shape[1:-1], n_iv).flatten(-2)
    init = batch_to_columns(init, prob.batch_lhs, prob.batch)
    b = torch.cat(
        [
            rhs.transpose(0, 1).reshape(L, T * E, R),
            init.transpose(0, 1).reshape(L, -1, R),
            rhs.new_zeros(L, m - T * E - init.shape[0] * init.shape[2], R),
        ],
        1,
    )
    mtb = mat.mT @ b
    mtb = torch.cat([mtb[:, :1] + gamma * alpha, mtb[:, 1:]], 1)
    y = _dense_cholesky_solve(mat.mT @ mat, mtb, "dense MNN solve")  # [L, n, R]
    u = columns_to_batch(y[:, 1:].reshape(L, T, B, R).transpose(0, 1), prob.batch_lhs, prob.batch)
    eps = columns_to_batch(y[None, :, :1], prob.batch_lhs, prob.batch)  # [1, *batch, 1]
    u = u.movedim(0, -2).reshape(*prob.batch, T, D, O)
    return u.to(out_dtype), eps.reshape(prob.batch).to(out_dtype)
