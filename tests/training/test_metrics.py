import math

import pytest
import torch

from mpsim.metrics import epochs_x_min_error, first_epoch_below, huber_loss, rollout_metrics


def test_huber_is_summed_over_time_and_features_and_averaged_over_node_trajectories():
    pred = torch.zeros(2, 3, 4, 2)
    target = torch.zeros(2, 3, 4, 2)
    target[:, 1:] = 0.5  # quadratic branch: 0.5 · 0.25 per element
    target[0, 0] = 100.0  # t0 is excluded
    # per node-trajectory: 2 steps × 2 features × 0.125 = 0.5
    assert huber_loss(pred, target).item() == pytest.approx(0.5)
    target[:, 1:] = 3.0  # linear branch: 3 − 0.5 = 2.5 per element → 4 × 2.5 = 10
    assert huber_loss(pred, target).item() == pytest.approx(10.0)


def test_epochs_x_min_error_is_epoch_times_error():
    out = epochs_x_min_error([1, 2, 3, 4], [0.5, 0.2, 0.3, math.nan])
    assert out == {"min_test_error": 0.2, "min_test_error_epoch": 2, "epochs_x_min_error": 0.4}
    assert first_epoch_below([1, 2, 3], [0.5, 0.2, 0.1], 0.25) == 2
    assert first_epoch_below([1, 2], [0.5, 0.4], 0.1) is None


def test_rollout_metrics_units_horizons_and_divergence():
    t = torch.arange(5.0)
    true = torch.zeros(3, 5, 2, 2)
    pred = true.clone()
    pred[:, 1:, :, 0] = 2.0  # error 2 in feature 0, whose std is 2 → normalised error 1
    pred[2, 3] = math.nan  # one diverged trajectory
    m = rollout_metrics(pred, true, torch.tensor([2.0, 1.0]), t, horizons=[2, 99])
    assert m["n_diverged"] == 1
    assert m["rmse"] == pytest.approx(math.sqrt(0.5))  # mean over features of (1², 0)
    assert m["rmse_raw"] == pytest.approx(math.sqrt(2.0))
    assert set(m["horizons"]) == {"2", "4"} and m["horizons"]["2"]["t"] == 2.0
    assert m["per_step_rmse"][0] == 0.0


def test_periodic_features_are_compared_on_the_circle():
    t = torch.arange(3.0)
    true = torch.zeros(1, 3, 1, 2)
    pred = true.clone()
    pred[:, 1:, 0, 0] = 2 * math.pi - 0.1  # a phase that wrapped once: true error 0.1
    pred[:, 1:, 0, 1] = 0.1
    m = rollout_metrics(pred, true, torch.ones(2), t, periods=[2 * math.pi, None])
    assert m["rmse"] == pytest.approx(0.1, rel=1e-5)
    assert rollout_metrics(pred, true, torch.ones(2), t)["rmse"] > 4  # without the period it is a huge error


def test_errors_on_the_measured_features_ignore_a_latent_one():
    """Issue 60: with only some states measured, a latent feature (estimated, not measured) is no target."""
    from mpsim.metrics import squared_errors, valid_prediction_time

    t = torch.arange(5.0)
    true = torch.zeros(2, 5, 1, 2)
    pred = true.clone()
    pred[:, 1:, :, 0] = 0.5  # the measured feature: error 0.5
    wild = pred.clone()
    wild[..., 1] = 1e3  # the latent one: anything
    std = torch.tensor([1.0, 2.0])
    for p in (pred, wild):
        m = rollout_metrics(p, true, std, t, horizons=[2], features=[0])
        assert m["rmse"] == pytest.approx(0.5) and m["horizons"]["2"]["rmse"] == pytest.approx(0.5)
        normalised, raw = squared_errors(p, true, std, features=[0])
        assert torch.allclose(normalised[:, 1:], torch.full((2, 4), 0.25))
        assert valid_prediction_time(p, true, std, t, threshold=0.3, features=[0]) == 1.0
    assert rollout_metrics(wild, true, std, t)["rmse"] > 100  # all features: the latent one counts
    assert valid_prediction_time(wild, true, std, t, threshold=0.3) == 0.0  # over at once
