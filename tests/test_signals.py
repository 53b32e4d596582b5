"""`mpsim.signals`: an input on a sample grid, held between samples (zoh) or interpolated (linear)."""

from __future__ import annotations

import pytest
import torch

from mpsim.errors import ConfigError
from mpsim.signals import GridInput, hold_at, input_hold


def test_zoh_holds_the_sample_at_or_before_and_linear_interpolates():
    t = torch.tensor([0.0, 1.0, 3.0], dtype=torch.float64)
    u = torch.tensor([1.0, 3.0, -1.0], dtype=torch.float64).reshape(1, 3, 1, 1).expand(2, 3, 2, 1)
    at = {s: torch.tensor(s, dtype=torch.float64) for s in (0.0, 0.5, 1.0, 2.0, 3.0, 4.0, -1.0)}
    zoh = {s: float(hold_at(t, u, v, "zoh")[0, 0, 0]) for s, v in at.items()}
    lin = {s: float(hold_at(t, u, v, "linear")[0, 0, 0]) for s, v in at.items()}
    assert zoh == {0.0: 1.0, 0.5: 1.0, 1.0: 3.0, 2.0: 3.0, 3.0: -1.0, 4.0: -1.0, -1.0: 1.0}
    assert lin == {0.0: 1.0, 0.5: 2.0, 1.0: 3.0, 2.0: 1.0, 3.0: -1.0, 4.0: -1.0, -1.0: 1.0}
    assert hold_at(t, u, at[0.5], "zoh").shape == (2, 2, 1)
    signal = GridInput(t, u, "linear")
    signal.held = 2  # an interval-by-interval solve fixes the sample
    assert float(signal(at[0.5])[0, 0, 0]) == -1.0


def test_the_hold_comes_from_the_data_and_defaults_to_linear():
    assert input_hold({}) == "linear" and input_hold(None) == "linear" and input_hold({"input_hold": "zoh"}) == "zoh"
    with pytest.raises(ConfigError, match="input_hold='foh' is not a hold; use data.input_hold=linear"):
        input_hold({"input_hold": "foh"})
