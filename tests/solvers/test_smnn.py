"""S-MNN banded and cyclic-reduction solvers: assembly, paper Table 3, agreement, gradients, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mpsim.bench.smnn_table3 import solver_inputs, table3_systems, truth
from mpsim.errors import MpsimError
from mpsim.metrics import relative_mse
from mpsim.solvers import smnn_cyclic
from mpsim.solvers.mnn_dense import dense_solve
from mpsim.solvers.smnn import (
    SolverError,
    assemble_blocks,
    banded_factor,
    banded_solve,
    choose_method,
    prepare_problem,
    smnn_solve,
)
from mpsim.solvers.smnn_cyclic import Chunked, chunk_length, cyclic_factor, cyclic_solve

F64 = torch.float64
METHODS = ("banded", "cyclic")


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().max() / b.abs().max())


def random_problem(T, E, D, O, S, I, batch=(), lhs_batch=None, seed=0):
    """Well-posed random S-MNN inputs (batch first); lhs_batch is the batch of coefficients and steps."""
    g = torch.Generator().manual_seed(seed)
    lhs_batch = batch if lhs_batch is None else lhs_batch
    coef = torch.randn(*lhs_batch, T, E, D, O, generator=g, dtype=F64)
    coef[..., 0] += 2.0  # keep every dimension tied to its value, so the polynomial null space is fixed
    rhs = torch.randn(*batch, T, E, generator=g, dtype=F64)
    init = torch.randn(*batch, S, D, I, generator=g, dtype=F64)
    steps = 0.1 + 0.2 * torch.rand(*lhs_batch, T - 1, generator=g, dtype=F64)
    return coef, rhs, init, steps


def oracle_rows(coef, rhs, init, steps, weights=(1.0, 1.0, 1.0), central=False):
    """Dense A and b built row by row from spec §1 (numpy, one unbatched problem)."""
    T, E, D, O = coef.shape
    S, I, K, N = init.shape[0], init.shape[-1], O - 1, T * D * O

    def col(t, d, k):
        return (t * D + d) * O + k

    rows, vals = [], []

    def add(entries, value, weight):
        row = np.zeros(N)
        for j, v in entries:
            row[j] += v
        rows.append(weight * row)
        vals.append(weight * value)

    for t in range(T):
        for e in range(E):
            add([(col(t, d, k), coef[t, e, d, k]) for d in range(D) for k in range(O)], rhs[t, e], weights[0])
    for s in range(S):
        for d in range(D):
            for k in range(I):
                add([(col(s, d, k), 1.0)], init[s, d, k], weights[1])
    for t in range(T - 1):
        h = steps[t]
        for d in range(D):
            for i in range(K if central else K + 1):
                fwd = [(col(t, d, j), h**j / math.factorial(j - i)) for j in range(i, O)]
                add(fwd + [(col(t + 1, d, i), -(h**i))], 0.0, weights[2])
                bwd = [(col(t + 1, d, j), (-h) ** j / math.factorial(j - i)) for j in range(i, O)]
                add(bwd + [(col(t, d, i), -((-h) ** i))], 0.0, weights[2])
    if central:
        for t in range(T - 2):
            H = steps[t] + steps[t + 1]
            for d in range(D):
                add(
                    [
                        (col(t, d, K - 1), H ** (K - 2)),
                        (col(t + 1, d, K), H ** (K - 1)),
                        (col(t + 2, d, K - 1), -(H ** (K - 2))),
                    ],
                    0.0,
                    weights[2],
                )
    return np.array(rows), np.array(vals)


# ---- assembly against the row-by-row definition ------------------------------------------------------------
@pytest.mark.parametrize("central", [False, True])
@pytest.mark.parametrize("O", [2, 3, 5])
def test_blocks_match_row_by_row_least_squares(central, O):
    coef, rhs, init, steps = random_problem(T=7, E=2, D=3, O=O, S=3, I=min(2, O), seed=O)
    weights = (1.3, 0.7, 1.9)
    A, b = oracle_rows(coef.numpy(), rhs.numpy(), init.numpy(), steps.numpy(), weights, central)
    ref = torch.from_numpy(np.linalg.lstsq(A, b, rcond=None)[0].reshape(7, 3, O))
    for method in METHODS:
        u = smnn_solve(
            coef,
            rhs,
            init,
            steps,
            weight_equation=1.3,
            weight_init_var=0.7,
            weight_smooth=1.9,
            central=central,
            method=method,
        )
        # O = 5 with h ≈ 0.2: cond(AᵀA) ~ h^-16, so only ~1e-8 is meaningful
        assert rel_err(u, ref) < (1e-7 if O == 5 else 1e-11), method


# ---- paper Table 3 (ODEBench linear ODEs, 1000 steps of 0.01, O = 3; systems in mpsim.bench.smnn_table3) ----
TABLE3 = table3_systems()


def _table3_inputs(name):
    return solver_inputs(TABLE3[name])


@pytest.mark.parametrize("name", list(TABLE3))
def test_table3_relative_mse(name):
    T, h = 1000, 0.01
    exact = truth(TABLE3[name], torch.arange(T, dtype=F64) * h)
    published = torch.tensor(TABLE3[name].published, dtype=F64)
    for method in METHODS:
        u = smnn_solve(*_table3_inputs(name), torch.tensor([h], dtype=F64), n_steps=T, method=method)
        # relMSE_k = mean_t (û_k − x⁽ᵏ⁾)² / Var_t(x⁽ᵏ⁾), variable x_0, orders k = 0, 1, 2
        rel_mse = relative_mse(u, exact)
        assert torch.allclose(rel_mse, ((u[:, 0, :] - exact) ** 2).mean(0) / exact.var(0, unbiased=False))
        ratio = rel_mse / published
        assert bool(((ratio > 1 / 3) & (ratio < 3)).all()), f"{method}: {rel_mse.tolist()} vs {published}"


@pytest.mark.parametrize("name", list(TABLE3))
def test_table3_banded_cyclic_dense_agree(name):
    """1000 steps for banded vs cyclic; the dense solver (cubic) on the first 300 steps."""
    coef, rhs, init = _table3_inputs(name)
    banded = smnn_solve(coef, rhs, init, 0.01, n_steps=1000, method="banded")
    assert rel_err(smnn_solve(coef, rhs, init, 0.01, n_steps=1000, method="cyclic"), banded) < 1e-9
    short = smnn_solve(coef, rhs, init, 0.01, n_steps=300)
    assert rel_err(dense_solve(coef, rhs, init, 0.01, n_steps=300), short) < 1e-9


@pytest.mark.slow
@pytest.mark.parametrize("name", list(TABLE3))
def test_table3_dense_full_length(name):
    coef, rhs, init = _table3_inputs(name)
    banded = smnn_solve(coef, rhs, init, 0.01, n_steps=1000)
    assert rel_err(dense_solve(coef, rhs, init, 0.01, n_steps=1000), banded) < 1e-9


# ---- agreement, broadcasting, layouts ----------------------------------------------------------------------
@pytest.mark.parametrize("central", [False, True])
@pytest.mark.parametrize("T", [2, 3, 5, 8, 33])
def test_three_solvers_agree_with_broadcast_lhs(central, T):
    # left-hand sides shared over the leading batch dim: batch_lhs = (1, 2), batch = (3, 2)
    coef, rhs, init, steps = random_problem(T, E=2, D=2, O=3, S=1, I=2, batch=(3, 2), lhs_batch=(1, 2), seed=T)
    kw = dict(central=central, weight_smooth=0.8, weight_equation=1.2)
    ref = dense_solve(coef, rhs, init, steps, **kw)
    assert ref.shape == (3, 2, T, 2, 3)
    for method in METHODS:
        assert rel_err(smnn_solve(coef, rhs, init, steps, method=method, **kw), ref) < 1e-9, method
    # the same problem with every left-hand side materialised per batch element
    full = smnn_solve(coef.expand(3, 2, *coef.shape[2:]), rhs, init, steps.expand(3, 2, T - 1), **kw)
    assert rel_err(full, ref) < 1e-12


def test_step_dim_first_layout_and_dtype():
    coef, rhs, init, steps = random_problem(6, E=1, D=2, O=3, S=2, I=1, batch=(4,), seed=3)
    u = smnn_solve(coef, rhs, init, steps)
    first = smnn_solve(
        coef.movedim(-4, 0), rhs.movedim(-2, 0), init.movedim(-3, 0), steps.movedim(-1, 0), step_dim_first=True
    )
    assert torch.equal(u, first)
    u32 = smnn_solve(coef.float(), rhs.float(), init.float(), steps.float())
    assert u32.dtype == torch.float32 and rel_err(u32.double(), u) < 1e-6  # computed in float64
    shared = smnn_solve(coef, rhs, init, torch.full((1,), 0.07, dtype=F64))
    assert torch.equal(smnn_solve(coef, rhs, init, 0.07), shared)  # a python float step stays float64


def test_broadcast_coefficients_over_time_and_iv_steps():
    """Size-1 step dims (coefficients, rhs, steps) and n_steps/n_init_var_steps overrides."""
    coef = torch.tensor([[[[0.3, 1.0, 0.0]]]], dtype=F64)  # 0.3 u + u' = 1
    u = smnn_solve(
        coef, torch.ones(1, 1, dtype=F64), torch.zeros(1, 1, 1, dtype=F64), 0.05, n_steps=40, n_init_var_steps=1
    )
    t = torch.arange(40, dtype=F64) * 0.05
    assert rel_err(u[:, 0, 0], (1 - torch.exp(-0.3 * t)) / 0.3) < 1e-4  # discretisation error at h = 0.05
    two = smnn_solve(coef, torch.ones(1, 1, dtype=F64), u[None, :2, :, :1], 0.05, n_steps=40)
    assert rel_err(two, u) < 1e-6  # two consistent initial steps give the same solution


def test_auto_picks_cyclic_for_thin_steps_and_banded_for_many_rhs():
    cpu = torch.device("cpu")
    assert choose_method(3, 3, 512, cpu) == "banded"  # Lorenz discovery: 3 matrices, 512 right-hand sides
    assert choose_method(1, 9, 1, cpu) == "cyclic"  # one trajectory: per-step dispatch dominates
    assert choose_method(1, 9, 1, cpu, n_steps=1000) == "cyclic"
    assert choose_method(1, 9, 1, cpu, n_steps=100) == "banded"  # short: the sweep is cheaper
    # one shared matrix, 1536 columns (the bench's Lorenz shapes): banded for windows, cyclic for long sequences
    assert choose_method(1, 3, 1536, cpu, n_steps=50) == "banded"
    assert choose_method(1, 3, 1536, cpu, n_steps=500) == "banded"
    assert choose_method(1, 3, 1536, cpu, n_steps=5000) == "cyclic"
    assert choose_method(1536, 3, 1, cpu, n_steps=5000) == "banded"  # one matrix per sample: factor-bound
    coef, rhs, init, steps = random_problem(40, E=1, D=1, O=3, S=1, I=1, seed=4)
    banded = smnn_solve(coef, rhs, init, steps, method="banded")
    assert rel_err(smnn_solve(coef, rhs, init, steps), banded) < 1e-10


# ---- chunked cyclic reduction ------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("T", "central", "lhs", "chunk"),
    [
        (40, False, (), 3),  # 10 full chunks, no tail
        (43, False, (2,), 2),  # two left-hand sides (step-major work buffer), a tail of one block
        (100, True, (), 4),  # central rows: paired 2B blocks
        (101, True, (3,), 5),  # odd T with central rows, tail
        (37, False, (), 16),  # the default chunk: two chunks and a long tail
    ],
)
def test_chunked_cyclic_matches_banded(T, central, lhs, chunk):
    coef, rhs, init, steps = random_problem(T, E=1, D=2, O=3, S=1, I=1, batch=(4, *lhs), lhs_batch=lhs or (1,), seed=T)
    prob = prepare_problem(
        coef,
        rhs,
        init,
        steps,
        n_steps=None,
        n_init_var_steps=None,
        weights=(1.0, 1.0, 1.0),
        central=central,
        step_dim_first=False,
        dtype=F64,
    )
    a0, a1, a2, beta = assemble_blocks(prob)
    fac, bad = cyclic_factor(a0, a1, a2, chunk=chunk)
    assert isinstance(fac.core, Chunked) and not bool(bad.any())
    ref = banded_solve(banded_factor(a0, a1, a2)[0], beta.contiguous())
    assert rel_err(cyclic_solve(fac, beta), ref) < 1e-11
    assert rel_err(cyclic_solve(fac, beta, refine=0), ref) < 1e-9


def test_chunk_length_keeps_a_cpu_sweep_step_in_cache():
    cpu, gpu = torch.device("cpu"), torch.device("cuda")
    assert chunk_length(5000, 24, cpu) == smnn_cyclic.CHUNK  # one thin trajectory: short chunks, depth O(log T)
    lorenz = chunk_length(5000, 3 * 1536 * 8, cpu)  # 512 windows x 3 variables: 37 KB a step
    assert lorenz > smnn_cyclic.CHUNK and -(-5000 // lorenz) * 3 * 1536 * 8 <= smnn_cyclic.SLAB_BYTES + 3 * 1536 * 8
    assert chunk_length(5000, 3 * 1536 * 8, gpu) == smnn_cyclic.CHUNK


@pytest.mark.parametrize("T", [12, 13])
def test_gradients_through_the_chunked_path(monkeypatch, T):
    monkeypatch.setattr(smnn_cyclic, "CHUNK", 2)
    coef, rhs, init, steps = random_problem(T=T, E=1, D=1, O=3, S=1, I=1, batch=(2,), lhs_batch=(1,), seed=T)
    args = [x.requires_grad_() for x in (coef, rhs, init, steps)]
    fn = lambda c, r, i, s: smnn_solve(c, r, i, s, method="cyclic")  # noqa: E731
    assert torch.autograd.gradcheck(fn, args, eps=1e-6, atol=1e-6, rtol=1e-5)


# ---- gradients ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("central", [False, True])
def test_gradcheck_finite_differences(method, central):
    coef, rhs, init, steps = random_problem(T=5, E=2, D=2, O=3, S=1, I=2, batch=(2,), lhs_batch=(1,), seed=7)
    args = [x.requires_grad_() for x in (coef, rhs, init, steps)]
    fn = lambda c, r, i, s: smnn_solve(c, r, i, s, central=central, method=method, weight_smooth=1.3)  # noqa: E731
    assert torch.autograd.gradcheck(fn, args, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_gradgradcheck_banded():
    coef, rhs, init, steps = random_problem(T=3, E=1, D=1, O=2, S=1, I=1, seed=8)
    args = [x.requires_grad_() for x in (coef, rhs, init, steps)]
    assert torch.autograd.gradgradcheck(lambda c, r, i, s: smnn_solve(c, r, i, s), args, atol=1e-5)


@pytest.mark.parametrize("central", [False, True])
def test_gradients_match_dense_autograd(central):
    coef, rhs, init, steps = random_problem(T=12, E=2, D=2, O=3, S=2, I=2, batch=(3, 2), lhs_batch=(1, 2), seed=11)
    weight = torch.randn(3, 2, 12, 2, 3, generator=torch.Generator().manual_seed(0), dtype=F64)
    grads = {}
    for name, solve in (
        ("dense", dense_solve),
        ("banded", smnn_solve),
        ("cyclic", lambda *a, **k: smnn_solve(*a, method="cyclic", **k)),
    ):
        args = [x.detach().requires_grad_() for x in (coef, rhs, init, steps)]
        (solve(*args, central=central, weight_init_var=2.0) * weight).sum().backward()
        grads[name] = [a.grad for a in args]
    for name in METHODS:
        for g, ref in zip(grads[name], grads["dense"], strict=True):
            assert rel_err(g, ref) < 1e-8, name


# ---- errors ------------------------------------------------------------------------------------------------
def test_singular_without_initial_value_names_the_missing_rows():
    coef = torch.tensor([[[[0.0, 1.0, 0.0]]]], dtype=F64)  # u' = r: a constant shift is free
    no_iv = torch.zeros(0, 1, 1, dtype=F64)
    with pytest.raises(SolverError, match=r"dimension 0: value\..*no initial-value rows") as err:
        smnn_solve(coef, torch.ones(1, 1, dtype=F64), no_iv, 0.1, n_steps=20)
    assert isinstance(err.value, MpsimError) and isinstance(err.value, ValueError)


def test_singular_without_any_rows():
    coef = torch.zeros(1, 0, 2, 3, dtype=F64)  # E = 0 equations, I = 0 orders
    msg = (
        "6 solution direction.*dimension 1: value, first derivative, second derivative.*"
        "no initial-value rows and no governing-equation rows"
    )
    with pytest.raises(SolverError, match=msg):
        smnn_solve(coef, torch.zeros(1, 0, dtype=F64), torch.zeros(1, 2, 0, dtype=F64), 0.1, n_steps=10)


def test_singular_missing_order_and_batch_index():
    coef = torch.tensor([[[[0.0, 0.0, 1.0]]]], dtype=F64).repeat(3, 1, 1, 1, 1)  # u'' = r for 3 elements
    coef[1, 0, 0, 0, 0] = 1.0  # element 1: u + u'' = r fixes every quadratic by itself
    coef[2, 0, 0, 0, 1] = 1.0  # element 2: u' + u'' = r, needs u(0) only
    init = torch.zeros(3, 1, 1, 1, dtype=F64)  # u(0) only
    with pytest.raises(SolverError, match=r"batch index \(0,\).*dimension 0: first derivative\."):
        smnn_solve(coef, torch.ones(3, 1, 1, dtype=F64), init, 0.1, n_steps=15)
    smnn_solve(coef[2:], torch.ones(1, 1, 1, dtype=F64), init[2:], 0.1, n_steps=15)  # well posed


@pytest.mark.parametrize("method", METHODS)
def test_non_finite_inputs_raise_instead_of_nan(method):
    coef, rhs, init, steps = random_problem(6, E=1, D=1, O=3, S=1, I=1, seed=2)
    rhs[3, 0] = float("nan")
    with pytest.raises(SolverError, match="not finite"):
        smnn_solve(coef, rhs, init, steps, method=method)
    coef[2, 0, 0, 1] = float("inf")
    with pytest.raises(SolverError):
        smnn_solve(coef, rhs, init, steps, method=method, check=False)


def test_invalid_arguments():
    coef, rhs, init, steps = random_problem(6, E=1, D=1, O=3, S=1, I=1, seed=2)
    with pytest.raises(SolverError, match="> 0"):
        smnn_solve(coef, rhs, init, -steps)
    with pytest.raises(SolverError, match="expected 1 or 6"):
        smnn_solve(coef, rhs[:4], init, steps)
    with pytest.raises(SolverError, match="Must be one of"):
        smnn_solve(coef, rhs, init, steps, method="sparse")
    with pytest.raises(SolverError, match="at least 2 time steps"):
        smnn_solve(coef[:1], rhs[:1], init, 0.1)
