"""Unmeasured states estimated from measured ones (`mpsim.data.latent`)."""

import numpy as np
import pytest
import torch

from mpsim.data.latent import MIN_WINDOW, estimate_latent, savgol_derivative, savgol_window
from mpsim.data.trajectories import Trajectories
from mpsim.errors import DataError


def _sine(dt=0.002, seconds=4.0, step=0.003, noise=0.001, seed=0):
    """A quantised noisy sine x = sin(πt) (an encoder of `step` with sensor noise) and its exact derivative."""
    t = np.arange(0, seconds, dt)
    x = np.sin(np.pi * t) + noise * np.random.default_rng(seed).standard_normal(len(t))
    if step:
        x = step * np.round(x / step)
    return t, x, np.pi * np.cos(np.pi * t)


def _data(t, columns, names):
    x = torch.as_tensor(np.stack(columns, axis=-1), dtype=torch.float64).reshape(1, len(t), 1, len(columns))
    return Trajectories(
        t=torch.as_tensor(t),
        x=x,
        edge_index=torch.zeros(2, 0, dtype=torch.long),
        meta={"state_names": names, "source": "s.csv"},
    )


def _relative_error(estimate, exact):
    return float(np.sqrt(np.mean((estimate - exact) ** 2) / np.mean(exact**2)))


@pytest.mark.parametrize(
    "dt, step, noise",
    [(0.002, 0.003, 0.001), (0.01, 0.003, 0.001), (0.001, 0.001, 0.0), (0.002, 0.0, 0.01)],
)
def test_window_rule_on_a_quantised_noisy_sine(dt, step, noise):
    t, x, exact = _sine(dt, step=step, noise=noise)
    o = torch.as_tensor(x).reshape(1, -1, 1)
    width = savgol_window(o, dt)
    estimate = savgol_derivative(o, dt, width)[0, :, 0].numpy()
    naive = np.gradient(x, dt)
    assert width % 2 == 1 and width >= MIN_WINDOW
    assert _relative_error(estimate, exact) < 0.03  # 1.7–2.7 % measured
    assert _relative_error(estimate, exact) < 0.5 * _relative_error(naive, exact)


def test_window_grows_with_the_noise():
    t, x_clean, _ = _sine(noise=0.0, step=0.0)
    _, x_noisy, _ = _sine(noise=0.01, step=0.0)
    widths = [savgol_window(torch.as_tensor(x).reshape(1, -1, 1), 0.002) for x in (x_clean, x_noisy)]
    assert widths[0] == MIN_WINDOW and widths[1] > 10 * MIN_WINDOW


def test_estimate_latent_fills_the_velocity_and_says_how():
    t, x, exact = _sine()
    out = estimate_latent(_data(t, [x], ["q"]), {"v": "q"}, states=["q", "v"])
    assert out.state_names == ["q", "v"] and out.x.shape == (1, len(t), 1, 2)
    assert torch.equal(out.x[..., 0], torch.as_tensor(x).reshape(1, -1, 1))  # the measured state as it was
    assert _relative_error(out.x[0, :, 0, 1].numpy(), exact) < 0.03
    assert out.meta["observed"] == ["q"]
    assert out.meta["estimated"]["v"].startswith("Savitzky–Golay derivative of q, window ")
    assert "polyorder 2" in out.meta["estimated"]["v"]
    fixed = estimate_latent(_data(t, [x], ["q"]), {"v": "q"}, window_s=0.05)
    assert "window 25 samples (0.05 s)" in fixed.meta["estimated"]["v"] and fixed.state_names == ["q", "v"]


def test_order_follows_the_model_and_measured_states_are_kept():
    t, x, _ = _sine()
    data = _data(t, [x, 2 * x], ["q", "v"])
    out = estimate_latent(data, {"v": "q"}, states=["v", "q"])  # v is measured: nothing to estimate
    assert out.meta["estimated"] == {} and torch.equal(out.x[..., 0], data.x[..., 1])


def test_latent_states_that_cannot_be_estimated_are_refused():
    t, x, _ = _sine()
    data = _data(t, [x], ["q"])
    with pytest.raises(
        DataError, match=r"state 'w' is not measured \(data.observed=\['q'\]\).*Add 'w' to data.observed"
    ):
        estimate_latent(data, {"v": "q"}, states=["q", "v", "w"])
    with pytest.raises(DataError, match=r"derivative of 'p' \(p' = v\), but 'p' is not measured either"):
        estimate_latent(data, {"v": "p"}, states=["q", "v"])
    uneven = _data(t**1.01 + t, [x], ["q"])
    with pytest.raises(DataError, match="needs a uniform time grid.*data.resample"):
        estimate_latent(uneven, {"v": "q"})


def test_the_measured_columns_travel_with_the_data():
    t, x, _ = _sine()
    out = estimate_latent(_data(t, [x], ["q"]), {"v": "q"}, states=["v", "q"])
    assert out.observed_index == [1] and out.latent_index == [0]
    for part in (out.subset([0]), out.time_slice(0, 10), out.to(dtype=torch.float32)):
        assert part.observed_index == [1] and part.meta["estimated"] == out.meta["estimated"]
    summary = out.measured_states()
    assert summary["observed"] == ["q"] and summary["estimated"]["v"].startswith("Savitzky–Golay derivative of q")
    full = _data(t, [x, x], ["q", "v"])
    assert full.observed_index == [0, 1] and full.latent_index == [] and full.measured_states() == {}
    bad = _data(t, [x, x], ["q", "v"])
    bad.meta["observed"] = ["w"]
    with pytest.raises(DataError, match=r"meta\['observed'\] = \['w'\] must name at least one of the states"):
        _ = bad.observed_index
