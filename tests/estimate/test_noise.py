"""`choose_process_noise`: the scale of Q by the measurements' likelihood, on a linear model whose Q is known."""

import pytest
import torch

from mpsim.estimate import choose_process_noise, kalman_smoother
from tests.estimate.test_kalman import Q as SHAPE
from tests.estimate.test_kalman import R, _maps, _sampled


@pytest.mark.parametrize("true_scale", [0.2, 5.0])
def test_the_chosen_scale_is_the_true_one(true_scale):
    """16 records of 100 samples drawn with process noise true_scale · Q; the search is given Q's shape only."""
    x, y, b = _sampled(16, 100, seed=2, process=true_scale * SHAPE)
    step, output = _maps(b, torch.float64)
    y, x0 = torch.as_tensor(y), torch.zeros(16, 2, dtype=torch.float64)
    choice = choose_process_noise(step, output, y, x0, torch.eye(2), SHAPE, R)
    assert not choice.at_edge
    assert choice.scale == pytest.approx(true_scale, rel=0.2)
    assert len(choice.scales) == len(choice.log_likelihood) == 9 + 2 * 2 + 1
    assert choice.log_likelihood.max().item() == pytest.approx(choice.smoothed.log_likelihood.sum().item())
    again = kalman_smoother(step, output, y, x0, torch.eye(2), choice.scale * torch.as_tensor(SHAPE), R)
    torch.testing.assert_close(again.mean, choice.smoothed.mean)


def test_a_best_scale_at_the_grids_edge_is_flagged():
    x, y, b = _sampled(4, 50, seed=3)
    step, output = _maps(b, torch.float64)
    y, x0 = torch.as_tensor(y), torch.zeros(4, 2, dtype=torch.float64)
    choice = choose_process_noise(step, output, y, x0, torch.eye(2), SHAPE, R, grid=[1e-4, 1e-3, 1e-2])
    assert choice.at_edge and choice.scale == 1e-2 and len(choice.scales) == 3
