"""Dense baselines: the S-MNN system solved densely, and the original MNN with a slack (spec §6.1)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mpsim.solvers.mnn_dense import DenseSizeError, dense_solve, mnn_dense_solve
from mpsim.solvers.smnn import SolverError, smnn_solve

F64 = torch.float64


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().max() / b.abs().max())


def random_problem(T, E, D, O, S, I, batch=(), seed=0):
    g = torch.Generator().manual_seed(seed)
    coef = torch.randn(*batch, T, E, D, O, generator=g, dtype=F64)
    coef[..., 0] += 2.0
    rhs = torch.randn(*batch, T, E, generator=g, dtype=F64)
    init = torch.randn(*batch, S, D, I, generator=g, dtype=F64)
    steps = 0.1 + 0.2 * torch.rand(*batch, T - 1, generator=g, dtype=F64)
    return coef, rhs, init, steps


def mnn_oracle(coef, rhs, init, steps, gamma_alpha=0.0):
    """y = [ε, u] from M and b built row by row as in mech-nn (numpy, one unbatched problem)."""
    T, E, D, O = coef.shape
    S, I, K, n = init.shape[0], init.shape[-1], O - 1, 1 + T * D * O

    def col(t, d, k):
        return 1 + (t * D + d) * O + k

    rows, vals = [], []

    def add(entries, value, slack):
        row = np.zeros(n)
        row[0] = slack
        for j, v in entries:
            row[j] += v
        rows.append(row)
        vals.append(value)

    for e in range(E):
        for t in range(T):
            add([(col(t, d, k), coef[t, e, d, k]) for d in range(D) for k in range(O)], rhs[t, e], 0.0)
    for s in range(S):
        for d in range(D):
            for k in range(I):
                add([(col(s, d, k), 1.0)], init[s, d, k], 0.0)
    for d in range(D):
        for i in range(K):
            for t in range(T - 1):  # forward Taylor rows
                h = steps[t]
                add(
                    [(col(t, d, j), h**j / math.factorial(j - i)) for j in range(i, O)] + [(col(t + 1, d, i), -(h**i))],
                    0.0,
                    1.0,
                )
            for t in range(1, T):  # backward Taylor rows
                h = steps[t - 1]
                add(
                    [(col(t, d, j), (-h) ** j / math.factorial(j - i)) for j in range(i, O)]
                    + [(col(t - 1, d, i), -((-h) ** i))],
                    0.0,
                    1.0,
                )
        for t in range(1, T - 1):  # central rows
            H = steps[t - 1] + steps[t]
            add(
                [
                    (col(t - 1, d, K - 1), -(H ** (K - 2))),
                    (col(t + 1, d, K - 1), H ** (K - 2)),
                    (col(t, d, K), -(H ** (K - 1))),
                ],
                0.0,
                1.0,
            )
    M, b = np.array(rows), np.array(vals)
    rhs_vec = M.T @ b
    rhs_vec[0] += gamma_alpha
    y = np.linalg.solve(M.T @ M, rhs_vec)
    return y[0], y[1:].reshape(T, D, O)


# ---- dense solver of the S-MNN system -------------------------------------------------------------------
@pytest.mark.parametrize("central", [False, True])
def test_dense_matches_banded(central):
    coef, rhs, init, steps = random_problem(9, E=2, D=2, O=3, S=2, I=2, batch=(3,), seed=1)
    kw = dict(central=central, weight_init_var=0.5)
    ref = smnn_solve(coef, rhs, init, steps, **kw)
    assert rel_err(dense_solve(coef, rhs, init, steps, **kw), ref) < 1e-10


def test_dense_refuses_before_allocating():
    coef = torch.tensor([0.0, 1.0, 0.0], dtype=F64).expand(1, 3, 1, 1, 1, 3)  # Lorenz shapes (spec §4.2)
    rhs, init = torch.zeros(512, 3, 5000, 1, dtype=F64), torch.zeros(512, 3, 1, 1, 1, dtype=F64)
    with pytest.raises(DenseSizeError, match=r"GiB.*max_bytes.*smnn_solve"):
        dense_solve(coef, rhs, init, 0.01, max_bytes=2**30)
    # per-sample left-hand sides as in mech-nn: 1536 dense 150x150 systems would need ~1 GiB
    with pytest.raises(DenseSizeError, match="1536 dense 150x150"):
        dense_solve(coef.expand(512, 3, 1, 1, 1, 3), rhs[:, :, :50], init, 0.01, max_bytes=2**28)
    with pytest.raises(DenseSizeError, match="dense MNN solve"):
        mnn_dense_solve(coef, rhs, init, 0.01, max_bytes=2**20)
    assert isinstance(DenseSizeError("x"), SolverError)


def test_dense_singular_message():
    coef = torch.tensor([[[[0.0, 1.0, 0.0]]]], dtype=F64)
    with pytest.raises(SolverError, match="dimension 0: value"):
        dense_solve(coef, torch.ones(1, 1, dtype=F64), torch.zeros(0, 1, 1, dtype=F64), 0.1, n_steps=8)


# ---- original MNN with slack ----------------------------------------------------------------------------
@pytest.mark.parametrize("O", [2, 3, 4])
def test_mnn_matches_row_by_row_oracle(O):
    coef, rhs, init, steps = random_problem(6, E=2, D=2, O=O, S=2, I=min(2, O), batch=(2,), seed=O)
    u, eps = mnn_dense_solve(coef, rhs, init, steps)
    assert u.shape == (2, 6, 2, O) and eps.shape == (2,)
    tol = 1e-7 if O == 4 else 1e-10  # normal equations: cond(MᵀM) grows like h^(-2K)
    for i in range(2):
        eps_ref, u_ref = mnn_oracle(*(x[i].numpy() for x in (coef, rhs, init, steps)))
        assert rel_err(u[i], torch.from_numpy(u_ref)) < tol
        assert abs(float(eps[i]) - eps_ref) < tol * max(1.0, abs(eps_ref))


def test_mnn_linear_slack_cost_and_shared_lhs():
    coef, rhs, init, steps = random_problem(5, E=1, D=1, O=3, S=1, I=1, seed=3)
    u, eps = mnn_dense_solve(coef, rhs, init, steps, gamma=0.5, alpha=0.1)
    eps_ref, u_ref = mnn_oracle(coef.numpy(), rhs.numpy(), init.numpy(), steps.numpy(), gamma_alpha=0.05)
    assert rel_err(u, torch.from_numpy(u_ref)) < 1e-9 and abs(float(eps) - eps_ref) < 1e-9
    # one shared left-hand side, several right-hand sides
    rhs4 = torch.randn(4, 5, 1, dtype=F64)
    u4, _ = mnn_dense_solve(coef, rhs4, init, steps)
    u1, _ = mnn_dense_solve(coef, rhs4[2], init, steps)
    assert rel_err(u4[2], u1) < 1e-12


def test_mnn_solves_a_linear_ode():
    """Harmonic oscillator x'' = −2.1 x from (0.4, −0.03), 200 steps of 0.01: close to the closed form."""
    coef = torch.tensor([[[[0, 1, 0], [-1, 0, 0]], [[2.1, 0, 0], [0, 1, 0]]]], dtype=F64)
    u, eps = mnn_dense_solve(
        coef, torch.zeros(1, 2, dtype=F64), torch.tensor([[[0.4], [-0.03]]], dtype=F64), 0.01, n_steps=200
    )
    t, w = torch.arange(200, dtype=F64) * 0.01, math.sqrt(2.1)
    exact = 0.4 * torch.cos(w * t) - 0.03 / w * torch.sin(w * t)
    assert rel_err(u[:, 0, 0], exact) < 1e-4 and abs(float(eps)) < 1e-6


def test_mnn_gradcheck():
    coef, rhs, init, steps = random_problem(4, E=1, D=1, O=3, S=1, I=2, seed=5)
    args = [x.requires_grad_() for x in (coef, rhs, init, steps)]
    assert torch.autograd.gradcheck(lambda *a: mnn_dense_solve(*a)[0], args, eps=1e-6, atol=1e-6, rtol=1e-5)
