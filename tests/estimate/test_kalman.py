"""`kalman_smoother` on linear-Gaussian models, where both smoothers must be the exact smoother: means, marginal
covariances and log-likelihood against the joint Gaussian over all states solved densely in numpy; the spread's
coverage; shapes, gaps and error messages."""

import numpy as np
import pytest
import torch

from mpsim.errors import DataError, DivergenceError
from mpsim.estimate import kalman_smoother
from tests.estimate.oracles import exact_smoother

A = np.array([[0.95, 0.2], [-0.2, 0.9]])  # a damped rotation
C = np.array([[1.0, 0.0], [0.5, 1.0]])
Q = np.array([[0.02, 0.005], [0.005, 0.03]])
R = np.array([[0.1, 0.02], [0.02, 0.2]])


def _linear(B=3, T=30, seed=0):
    """B records of x_{k+1} = A x_k + b_k, y = C x (inputs b, priors and measurements differ per record), with gaps:
    record 0 misses samples 0 and 5–8 entirely, record 1 its second channel every fourth sample, the last one value
    (for T > 10)."""
    rng = np.random.default_rng(seed)
    b = rng.normal(size=(B, T - 1, 2))
    x0 = rng.normal(size=(B, 2))
    P0 = np.stack([np.array([[1.0 + i, 0.3], [0.3, 0.5 + i]]) for i in range(B)])
    y = rng.normal(size=(B, T, 2)) * 2
    if T > 10:
        y[0, 0] = y[0, 5:9] = np.nan
        y[1, 3::4, 1] = np.nan
        y[-1, 10, 0] = np.nan
    return b, x0, P0, y


def _maps(b, dtype):
    tA, tb, tC = (torch.as_tensor(a, dtype=dtype) for a in (A, b, C))
    return (lambda x, k: x @ tA.mT + tb[:, k, None, :]), (lambda x, k: x @ tC.mT)


@pytest.mark.parametrize("method", ["ekf", "ukf"])
@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-9), (torch.float32, 1e-4)])
def test_linear_model_gives_the_exact_smoother(method, dtype, tol):
    b, x0, P0, y = _linear()
    step, output = _maps(b, dtype)
    cast = lambda a: torch.as_tensor(a, dtype=dtype)  # noqa: E731
    s = kalman_smoother(step, output, cast(y), cast(x0), cast(P0), cast(Q), cast(R), method=method)
    assert s.mean.dtype == s.cov.dtype == s.log_likelihood.dtype == dtype
    for i in range(len(y)):
        mean, cov, log_likelihood = exact_smoother(A, b[i], C, y[i], x0[i], P0[i], Q, R)
        np.testing.assert_allclose(s.mean[i].double().numpy(), mean, atol=tol * np.abs(mean).max(), rtol=0)
        np.testing.assert_allclose(s.cov[i].double().numpy(), cov, atol=tol * np.abs(cov).max(), rtol=0)
        assert s.log_likelihood[i].item() == pytest.approx(log_likelihood, rel=tol)
    assert torch.linalg.eigvalsh(s.cov).min() > 0


@pytest.mark.parametrize("method", ["ekf", "ukf"])
def test_iterating_a_linear_model_changes_nothing(method):
    b, x0, P0, y = _linear(T=15)
    step, output = _maps(b, torch.float64)
    args = (torch.as_tensor(y), torch.as_tensor(x0), torch.as_tensor(P0), torch.as_tensor(Q), torch.as_tensor(R))
    once = kalman_smoother(step, output, *args, method=method)
    thrice = kalman_smoother(step, output, *args, method=method, iterations=3)
    torch.testing.assert_close(thrice.mean, once.mean, atol=1e-9, rtol=0)
    torch.testing.assert_close(thrice.cov, once.cov, atol=1e-9, rtol=0)


def _sampled(B, T, seed, process=Q):
    """B records drawn from the linear-Gaussian model itself (prior N(0, I), process noise of covariance `process`,
    measurement noise R): the truth [B, T, 2], the measurements [B, T, 2] and each record's input b [B, T-1, 2]."""
    rng = np.random.default_rng(seed)
    b = rng.normal(size=(B, T - 1, 2)) * 0.3
    x = np.empty((B, T, 2))
    x[:, 0] = rng.multivariate_normal([0.0, 0.0], np.eye(2), size=B)
    for k in range(T - 1):
        x[:, k + 1] = x[:, k] @ A.T + b[:, k] + rng.multivariate_normal([0, 0], process, size=B)
    y = x @ C.T + rng.multivariate_normal([0, 0], R, size=(B, T))
    return x, y, b


@pytest.mark.parametrize("method", ["ekf", "ukf"])
def test_the_spread_is_honest(method):
    """Over 200 records of 50 samples drawn from the model (fixed seed), the truth lies within ±2σ of the smoothed
    mean for 95.4 % of the samples of each state, and within ±1σ for 68.3 %."""
    x, y, b = _sampled(200, 50, seed=1)
    step, output = _maps(b, torch.float64)
    s = kalman_smoother(
        step, output, torch.as_tensor(y), torch.zeros(200, 2, dtype=torch.float64), torch.eye(2), Q, R, method
    )
    error = (s.mean - torch.as_tensor(x)).abs()
    within2 = (error <= 2 * s.std).double().mean(dim=(0, 1))
    within1 = (error <= s.std).double().mean(dim=(0, 1))
    assert ((within2 > 0.945) & (within2 < 0.962)).all(), within2
    assert ((within1 > 0.665) & (within1 < 0.70)).all(), within1


def test_a_record_without_measurements_is_its_prior_run_forward():
    b, x0, P0, y = _linear(B=2, T=10)
    y[1] = np.nan
    step, output = _maps(b, torch.float64)
    s = kalman_smoother(step, output, torch.as_tensor(y), torch.as_tensor(x0), torch.as_tensor(P0), Q, R)
    mean, cov = x0[1], P0[1]
    for k in range(10):
        np.testing.assert_allclose(s.mean[1, k].numpy(), mean, atol=1e-9)
        np.testing.assert_allclose(s.cov[1, k].numpy(), cov, atol=1e-9)
        if k < 9:
            mean, cov = A @ mean + b[1, k], A @ cov @ A.T + Q
    assert s.log_likelihood[1].item() == 0.0


def test_shared_and_per_record_covariances_agree_and_one_sample_is_one_update():
    b, x0, P0, y = _linear(B=2, T=1)
    step, output = _maps(b, torch.float64)
    y, x0 = torch.as_tensor(y), torch.as_tensor(x0)
    shared = kalman_smoother(step, output, y, x0, torch.eye(2), Q, R)
    batched = kalman_smoother(step, output, y, x0, torch.eye(2).expand(2, 2, 2), torch.as_tensor(Q).expand(2, 2, 2), R)
    torch.testing.assert_close(shared.mean, batched.mean)
    assert shared.mean.shape == (2, 1, 2) and shared.cov.shape == (2, 1, 2, 2)
    # T = 1: the smoother is one Kalman update of the prior N(x0, I)
    gain = np.linalg.solve(C @ C.T + R, C).T
    seen = 1  # record 1's only sample is fully measured
    expected = x0[seen].numpy() + gain @ (y[seen, 0].numpy() - C @ x0[seen].numpy())
    np.testing.assert_allclose(shared.mean[seen, 0].numpy(), expected, atol=1e-12)


def test_wrong_arguments_say_what_to_pass():
    b, x0, P0, y = _linear(B=2, T=5)
    step, output = _maps(b, torch.float64)
    y, x0 = torch.as_tensor(y), torch.as_tensor(x0)
    with pytest.raises(DataError, match="method must be one of"):
        kalman_smoother(step, output, y, x0, torch.eye(2), Q, R, method="pf")
    with pytest.raises(DataError, match=r"Q must be \[2, 2\] or \[2, 2, 2\]"):
        kalman_smoother(step, output, y, x0, torch.eye(2), torch.eye(3), R)
    with pytest.raises(DataError, match="y must be"):
        kalman_smoother(step, output, y[0], x0, torch.eye(2), Q, R)
    with pytest.raises(DataError, match="same B and R"):
        kalman_smoother(lambda x, k: x[:, :1], output, y, x0, torch.eye(2), Q, R)
    with pytest.raises(DataError, match=r"step function must map .* \[B, R, 2\].*whole state"):
        kalman_smoother(lambda x, k: x[..., :1], output, y, x0, torch.eye(2), Q, R)
    with pytest.raises(DataError, match=r"output function .* \[B, R, 2\].* sets P"):
        kalman_smoother(step, lambda x, k: x[..., :1], y, x0, torch.eye(2), Q, R)
    with pytest.raises(DivergenceError, match="NaN or inf at sample 2"):
        kalman_smoother(lambda x, k: x / (2 - k), output, y, x0, torch.eye(2), Q, R)
    with pytest.raises(DivergenceError, match="not positive definite"):
        kalman_smoother(step, output, y, x0, torch.eye(2), Q, -torch.eye(2))


def _on(device, method):
    b, x0, P0, y = _linear()
    cast = lambda a: torch.as_tensor(a, dtype=torch.float64, device=device)  # noqa: E731
    tA, tb, tC = cast(A), cast(b), cast(C)
    step, output = (lambda x, k: x @ tA.mT + tb[:, k, None, :]), (lambda x, k: x @ tC.mT)
    return kalman_smoother(step, output, cast(y), cast(x0), cast(P0), cast(Q), cast(R), method=method)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.parametrize("method", ["ekf", "ukf"])
def test_on_a_gpu_it_is_the_cpu_smoother(method):
    cpu, gpu = _on("cpu", method), _on("cuda", method)
    assert gpu.mean.device.type == "cuda"
    torch.testing.assert_close(gpu.mean.cpu(), cpu.mean, atol=1e-9, rtol=0)
    torch.testing.assert_close(gpu.log_likelihood.cpu(), cpu.log_likelihood, atol=1e-8, rtol=0)


def test_the_docstring_example_runs():
    import doctest

    import mpsim.estimate.kalman as module

    assert doctest.testmod(module, raise_on_error=True).attempted >= 5
