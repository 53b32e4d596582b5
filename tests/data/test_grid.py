"""Resampling, striding and uniform grids of measured recordings (`mpsim.data.grid`)."""

import numpy as np
import pytest
import torch

from mpsim.data.grid import JITTER_RTOL, resample, stride, uniform_fit, uniform_or_refuse
from mpsim.data.trajectories import Trajectories, grid_step
from mpsim.errors import ConfigError, DataError


def _rec(t, x, u=None, source="r.csv"):
    t = torch.as_tensor(t, dtype=torch.float64)
    x = torch.as_tensor(x, dtype=torch.float64).reshape(1, len(t), 1, -1)
    u = None if u is None else torch.as_tensor(u, dtype=torch.float64).reshape(1, len(t), 1, -1)
    meta = {
        "source": source,
        "dt": float((t[1:] - t[:-1]).median()),
        "state_names": [f"s{i}" for i in range(x.shape[-1])],
    }
    return Trajectories(t=t, x=x, edge_index=torch.zeros(2, 0, dtype=torch.long), u=u, meta=meta)


def test_resample_interpolates_states_linearly_and_holds_inputs():
    t = [10.0, 10.3, 10.5, 11.25]  # absolute, uneven
    rec = _rec(t, [0.0, 3.0, 5.0, 12.5], u=[1.0, 2.0, 3.0, 4.0])
    lin = resample(rec, 0.25)
    assert lin.t.tolist() == [10.0, 10.25, 10.5, 10.75, 11.0, 11.25]  # from the first to the last time
    assert torch.allclose(lin.x[0, :, 0, 0], torch.tensor([0.0, 2.5, 5.0, 7.5, 10.0, 12.5], dtype=torch.float64))
    assert torch.allclose(
        lin.u[0, :, 0, 0], torch.tensor([1.0, 1 + 0.25 / 0.3, 3.0, 3 + 1 / 3, 3 + 2 / 3, 4.0], dtype=torch.float64)
    )
    zoh = resample(rec, 0.25, hold="zoh")  # the sample at or before each new time
    assert zoh.u[0, :, 0, 0].tolist() == [1.0, 1.0, 3.0, 3.0, 3.0, 4.0]
    assert torch.equal(zoh.x, lin.x) and lin.meta["dt"] == 0.25 and grid_step(lin.t) == pytest.approx(0.25)
    assert rec.t.tolist() == t  # the input is unchanged


def test_resample_onto_the_same_grid_keeps_every_value():
    t = np.arange(0, 2.0001, 0.01)
    x = np.random.default_rng(0).standard_normal(len(t))
    back = resample(_rec(t, x), 0.01)
    assert back.n_times == len(t) and np.allclose(back.x[0, :, 0, 0].numpy(), x, rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "dt, hold, match",
    [
        (0.0, "linear", "data.resample must be"),
        (0.1, "cubic", "data.input_hold"),
        (5.0, "linear", "fewer than 2 samples"),
    ],
)
def test_resample_refuses_bad_settings(dt, hold, match):
    with pytest.raises(ConfigError, match=match):
        resample(_rec([0.0, 0.5, 1.0], [0.0, 1.0, 2.0]), dt, hold=hold)


def test_stride_keeps_every_kth_sample():
    rec = _rec(np.arange(10) * 0.1, np.arange(10.0), u=np.arange(10.0) * 2)
    out = stride(rec, 3)
    assert out.x[0, :, 0, 0].tolist() == [0.0, 3.0, 6.0, 9.0] and out.u[0, :, 0, 0].tolist() == [0.0, 6.0, 12.0, 18.0]
    assert out.meta["dt"] == pytest.approx(0.3) and out.meta["stride"] == 3
    assert stride(rec, 1) is rec
    for bad in (0, 2.5, True):
        with pytest.raises(ConfigError, match="data.stride must be a whole number"):
            stride(rec, bad)
    with pytest.raises(ConfigError, match="data.stride=10 leaves fewer than 2"):
        stride(rec, 10)


def test_uniform_or_refuse_snaps_small_jitter_and_refuses_a_gap():
    t = np.arange(100) * 0.002
    jitter = t + 0.002 * 0.01 * np.sin(np.arange(100))  # 1 % of a step, as the DFKI recordings
    out = uniform_or_refuse(_rec(jitter, np.arange(100.0)))
    assert np.isfinite(grid_step(out.t)) and out.meta["jitter"] <= 0.012
    assert np.abs(out.t.numpy() - jitter).max() <= 0.012 * 0.002 and out.meta["dt"] == pytest.approx(0.002, rel=1e-4)
    gap = t.copy()
    gap[1:] += 0.017  # the first step is 19 ms instead of 2 (as sac_200Hz.csv)
    _, off, _ = uniform_fit(torch.as_tensor(gap))
    assert off > JITTER_RTOL
    with pytest.raises(
        DataError,
        match=r"r.csv: the sampling is not uniform: row \d+ .* % of a step.*"
        r"data.resample=<dt>, e.g. data.resample=0.002 \(the median step\)\.",
    ):
        uniform_or_refuse(_rec(gap, np.arange(100.0)))


def test_stride_averages_an_input_held_zoh_over_the_samples_each_kept_one_stands_for():
    # a closed-loop input that changes every sample: picking every 3rd value would replay another input than the
    # one applied; the mean over each block of 3 applies the same impulse over the coarse step
    u = np.array([1.0, 2.0, 6.0, 0.0, 3.0, 3.0, -3.0, 0.0, 0.0, 9.0])
    rec = _rec(np.arange(10) * 0.1, np.arange(10.0), u=u)
    out = stride(rec, 3, hold="zoh")
    assert out.u[0, :, 0, 0].tolist() == pytest.approx([3.0, 2.0, -1.0, 9.0])  # the last block holds one sample
    assert out.x[0, :, 0, 0].tolist() == [0.0, 3.0, 6.0, 9.0] and out.meta["input_averaged"] == 3
    # the impulse over every whole block is the fine input's
    assert float(out.u[0, :3, 0, 0].sum() * 0.3) == pytest.approx(float(u[:9].sum() * 0.1))
    assert stride(rec, 3, hold="linear").u[0, :, 0, 0].tolist() == [1.0, 0.0, -3.0, 9.0]  # band-limited: picked
