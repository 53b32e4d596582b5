"""`system.input`: the signal generators of a driven twin (multisine, steps, chirp, PRBS) and their checks."""

from __future__ import annotations

import math

import pytest
import torch

from mpsim.errors import ConfigError
from mpsim.systems.inputs import MLS_TAPS, InputSignals, _mls_bits


def _draw(config, t, n=4, nodes=2, seed=0):
    return InputSignals(config, ["u"]).sample(t, n, nodes, seed)[..., 0]  # [B, T, N]


T = torch.arange(0, 200.0, 0.05, dtype=torch.float64)


def test_multisine_has_its_band_and_rms_and_random_phases():
    u = _draw({"kind": "multisine", "band": [0.5, 1.5], "components": 5, "rms": 0.7}, T)
    assert u.shape == (4, T.numel(), 2)
    rms = u.pow(2).mean(1).sqrt()
    assert torch.allclose(rms, torch.full_like(rms, 0.7), rtol=0.02)
    spectrum = torch.fft.rfft(u[0, :, 0]).abs()
    freqs = torch.fft.rfftfreq(T.numel(), 0.05)
    inside = (freqs >= 0.45) & (freqs <= 1.55)
    assert float(spectrum[inside].pow(2).sum() / spectrum.pow(2).sum()) > 0.99
    assert not torch.allclose(u[0, :, 0], u[0, :, 1]) and not torch.allclose(u[0, :, 0], u[1, :, 0])
    fixed = _draw({"kind": "multisine", "band": [1.0, 1.0], "components": 1, "amplitude": 2.0, "offset": 3.0}, T)
    assert float(fixed.max()) == pytest.approx(5.0, abs=1e-3) and float(fixed.min()) == pytest.approx(1.0, abs=1e-3)


def test_steps_hold_random_levels_for_random_durations():
    u = _draw({"kind": "steps", "levels": [2.0, 5.0], "duration": [1.0, 3.0]}, T, n=2, nodes=1)[:, :, 0]
    assert float(u.min()) >= 2.0 and float(u.max()) <= 5.0
    for row in u:  # a loop over two realisations
        change = torch.nonzero(row[1:] != row[:-1])[:, 0] + 1  # first sample of every new level
        lengths = (change[1:] - change[:-1]).double() * 0.05
        assert len(lengths) > 40 and float(lengths.min()) >= 1.0 - 0.051 and float(lengths.max()) <= 3.0 + 0.051


def test_chirp_sweeps_from_f0_to_f1():
    u = _draw({"kind": "chirp", "f0": 0.1, "f1": 2.0, "amplitude": 1.5}, T, n=1, nodes=1)[0, :, 0]
    assert float(u.abs().max()) <= 1.5 + 1e-12
    crossings = (u[1:] * u[:-1] < 0).double()
    n = T.numel() // 10
    assert crossings[:n].sum() < crossings[-n:].sum() / 5  # the end oscillates much faster than the start
    assert float(crossings[-n:].sum()) == pytest.approx(2 * 2.0 * 20, rel=0.1)  # ≈ 2·f1 crossings per second


def test_prbs_switches_only_on_its_clock_between_plus_and_minus_amplitude():
    u = _draw({"kind": "prbs", "amplitude": 0.5, "clock": 0.2}, T, n=3, nodes=1)[:, :, 0]
    assert set(u.unique().tolist()) == {-0.5, 0.5}
    change = torch.nonzero((u[:, 1:] != u[:, :-1]).any(0))[:, 0] + 1
    assert bool((change % 4 == 0).all())  # every 4th sample of 0.05 is a clock edge of 0.2
    assert not torch.equal(u[0], u[1])
    rand = _draw({"kind": "prbs", "sequence": "random"}, T, n=3, nodes=1)
    assert set(rand.unique().tolist()) == {-1.0, 1.0}


@pytest.mark.parametrize("order", [3, 7, 10])
def test_mls_bits_are_a_maximal_length_sequence(order):
    period = 2**order - 1
    assert _mls_bits(period, 1, torch.Generator()).shape == (1, period)  # the order whose period covers the record
    bits = _mls_bits(2 * period, 3, torch.Generator().manual_seed(0), order=order)
    assert torch.equal(bits[:, :period], bits[:, period:])  # periodic with 2^m − 1 ...
    assert bits[:, :period].sum(1).tolist() == [2 ** (order - 1)] * 3  # ... and balanced: one more 1 than 0s
    ones = bits[0, :period].tolist()
    windows = {tuple(ones[(i + j) % period] for j in range(order)) for i in range(period)}
    assert len(windows) == period  # every nonzero m-bit word appears once: maximal length
    assert order in MLS_TAPS


def test_draws_are_reproducible_and_follow_both_seeds():
    config = {"kind": "multisine", "seed": 4}
    a, b = _draw(config, T[:50], seed=1), _draw(config, T[:50], seed=1)
    assert torch.equal(a, b)
    assert not torch.equal(a, _draw(config, T[:50], seed=2))
    assert not torch.equal(a, _draw({**config, "seed": 5}, T[:50], seed=1))


@pytest.mark.parametrize(
    "config, message",
    [
        ({"kind": "multisine", "band": [2.0, 1.0]}, "band must be [low, high] with low <= high"),
        ({"kind": "multisine", "band": [0.0, 1.0]}, "band must be a positive finite number"),
        ({"kind": "multisine", "components": 0}, "components must be an integer from 1 to 10000"),
        ({"kind": "steps", "duration": [1.0]}, "duration must be [low, high]"),
        ({"kind": "chirp", "amplitude": -1}, "amplitude must be a positive finite number"),
        ({"kind": "prbs", "clock": 0}, "clock must be a positive finite number"),
        ({"kind": "chirp", "seed": 1.5}, "seed must be an integer"),
        ({"kind": "chirp", "offset": math.inf}, "offset must be a finite number"),
        ({"file": ""}, "file must be the path of a CSV file"),
        ({"kind": "multisne"}, "Did you mean 'multisine'"),
    ],
)
def test_bad_signal_keys_get_one_clear_message(config, message):
    with pytest.raises(ConfigError) as err:
        InputSignals(config, ["u"])
    assert message in str(err.value) and "system.input" in str(err.value)
