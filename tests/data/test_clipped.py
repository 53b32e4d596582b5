"""Clipped samples found in a recording as read (issue 72, item 2): a sensor's flat tops, not a quantised peak."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mpsim.data.account import account_lines
from mpsim.data.clipped import clipped_channels
from tests.helpers import run_mpsim


def _wave(n: int = 2000, per: int = 200) -> torch.Tensor:  # [T] a sine with a second harmonic, 10 periods
    k = torch.arange(n, dtype=torch.float64) * 2 * math.pi / per
    return torch.sin(k) + 0.3 * torch.sin(2 * k + 0.5)


def test_a_level_sensor_at_its_limit_is_clipped_and_a_quantised_peak_is_not():
    v = _wave()
    top = float(v.max()) * 0.9
    clipped = v.clamp(max=top)  # the sensor reads its limit at every peak
    quantised = torch.round(v / 0.01) * 0.01  # a smooth signal on a 0.01 grid: its top value repeats at each peak
    noisy = v + 0.001 * torch.randn(v.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    x = torch.stack([clipped, quantised, noisy], dim=1)  # [T, 3]
    (found,) = clipped_channels(x, ["h", "q", "y"])
    assert (found["channel"], found["side"], found["runs"]) == ("h", "max", 10)
    assert found["value"] == top and found["samples"] == int((clipped == top).sum())
    assert clipped_channels(x[:, 1:], ["q", "y"]) == []


def test_the_account_names_the_clipped_channel_of_its_file():
    entry = {"file": "tanks.csv", "rows": 500, "span": [0.0, 499.0], "pieces": []}
    entry["clipped"] = [{"channel": "h2", "side": "max", "value": 10.0, "runs": 3, "samples": 41, "share": 0.082}]
    (line,) = account_lines({"files": [entry]})
    assert "h2 reads its maximum 10 in 3 runs of 3 or more identical samples (41 samples, 8.2 %)" in line


@pytest.mark.slow  # a training run on the command line: `pytest -m slow` (.ci/run runs it)
def test_the_account_and_the_log_say_which_samples_look_clipped(tmp_path):
    t = np.arange(2000) * 0.01
    u = np.sin(0.7 * t) + 0.5 * np.sin(2.3 * t)
    q = np.minimum(np.sin(0.7 * t - 0.3) + 0.4 * np.sin(2.3 * t - 0.8), 1.0)  # an encoder at its end stop
    lines = ["t,q,u", *(f"{a:.2f},{b:.6f},{c:.6f}" for a, b, c in zip(t, q, u, strict=True))]
    (tmp_path / "axis.csv").write_text("\n".join(lines) + "\n")
    spec = "model.spec={states: [q], inputs: [u], equations: {q: -a*q + u}, params: {a: 1.0}, learnable: [a]}"
    proc = run_mpsim(
        ["train", "model=equations", spec, "data.path=axis.csv", "data.control_columns=[u]", "trainer.max_epochs=1",
         "trainer=whitebox", "eval.plots=false", "data.segment=2.0"], tmp_path,
    )  # fmt: skip
    assert proc.code == 0, proc.err[-2000:]
    said = proc.out + proc.err
    assert "q reads its maximum 1 in" in said and "They are fitted as they are" in said
