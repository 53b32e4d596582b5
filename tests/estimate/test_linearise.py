"""The affine approximations under the smoothers: central-difference Jacobians (EKF) and the unscented statistical
linear regression (UKF), against closed forms."""

import pytest
import torch

from mpsim.estimate.linearise import linearise

F64 = torch.float64


def _field(x, k):  # x [B, R, 2] -> [B, R, 2]: a smooth nonlinear map with a known Jacobian
    return torch.stack([torch.sin(x[..., 0]) * x[..., 1], x[..., 0] ** 2 + k * x[..., 1]], -1)


@pytest.mark.parametrize("dtype, tol", [(F64, 1e-9), (torch.float32, 1e-3)])
def test_ekf_slope_is_the_jacobian(dtype, tol):
    mean = torch.tensor([[0.3, -1.2], [2.0, 0.5]], dtype=dtype)
    cov = torch.eye(2, dtype=dtype).expand(2, 2, 2) * 0.1
    lin = linearise(_field, 3, mean, cov, "ekf", "step", 2)
    a, b = mean[:, 0], mean[:, 1]
    jacobian = torch.stack(
        [torch.stack([torch.cos(a) * b, torch.sin(a)], -1), torch.stack([2 * a, torch.full_like(a, 3.0)], -1)], -2
    )
    torch.testing.assert_close(lin.slope, jacobian, atol=tol, rtol=tol)
    torch.testing.assert_close(lin.value, _field(mean[:, None], 3)[:, 0])
    assert lin.extra is None and lin.point is mean


def test_ukf_on_a_square_is_its_exact_regression():
    """For x ~ N(m, s²) and f(x) = x², the regression slope is 2m, the mean m² + s² and the residual variance 2s⁴:
    the unscented transform with β = 2 gets all three exactly."""
    m, s = torch.tensor([[0.7], [-2.0]], dtype=F64), torch.tensor([0.5, 1.5], dtype=F64)
    lin = linearise(lambda x, k: x**2, 0, m, (s**2)[:, None, None], "ukf", "output", 1)
    torch.testing.assert_close(lin.slope[:, 0, 0], 2 * m[:, 0])
    torch.testing.assert_close(lin.value[:, 0], m[:, 0] ** 2 + s**2)
    torch.testing.assert_close(lin.extra[:, 0, 0], 2 * s**4)


def test_ukf_on_a_linear_map_is_that_map():
    M = torch.tensor([[1.0, 2.0, 0.0], [0.5, -1.0, 3.0]], dtype=F64)
    mean = torch.tensor([[0.1, 0.2, 0.3]], dtype=F64)
    cov = torch.tensor([[[2.0, 0.5, 0.1], [0.5, 1.0, 0.2], [0.1, 0.2, 0.5]]], dtype=F64)
    lin = linearise(lambda x, k: x @ M.mT + 1.0, 0, mean, cov, "ukf", "output", 2)
    torch.testing.assert_close(lin.slope[0], M)
    torch.testing.assert_close(lin.value, mean @ M.mT + 1.0)
    torch.testing.assert_close(lin.extra, torch.zeros(1, 2, 2, dtype=F64), atol=1e-12, rtol=0)
