"""Noise level and quantisation of measured data (`mpsim.data.noise`)."""

import numpy as np
import pytest
import torch

from mpsim.data.noise import grid_quantum, noise_summary
from mpsim.data.trajectories import Trajectories
from mpsim.diagnose import noise as diagnose_noise


def test_grid_quantum_finds_the_encoder_step_with_offset_and_skipped_levels():
    t = np.linspace(0, 4, 2000)
    step = 0.02198
    levels = np.round(3 * np.sin(t) / step)
    assert grid_quantum(torch.as_tensor((levels + 0.5) * step)) == pytest.approx(step, rel=1e-9)  # half-step offset
    only_even = 2 * np.round(levels / 2)  # alternate levels never visited: all the data show is a grid of 2 steps
    assert grid_quantum(torch.as_tensor(only_even * step)) == pytest.approx(2 * step, rel=1e-9)
    odd = np.unique(np.abs(only_even))[1:6] + 1  # a few odd levels visited: the smallest gap is one step
    some_odd = np.concatenate([only_even, odd]) * step
    assert grid_quantum(torch.as_tensor(some_odd)) == pytest.approx(step, rel=1e-9)
    smeared = (levels + 0.3 * np.random.default_rng(0).uniform(size=len(levels))) * step
    assert grid_quantum(torch.as_tensor(smeared)) is None
    assert grid_quantum(torch.as_tensor(np.sin(t))) is None  # continuous readings sit on no grid


def test_noise_summary_per_state_and_input():
    rng = np.random.default_rng(0)
    t = np.arange(0, 10, 0.01)
    q = 0.003 * np.round(np.sin(t) / 0.003)
    v = np.cos(t) + 0.05 * rng.standard_normal(len(t))
    x = torch.as_tensor(np.stack([q, v], -1)).reshape(1, -1, 1, 2)
    u = torch.as_tensor(0.01 * np.round(np.sin(3 * t) / 0.01)).reshape(1, -1, 1, 1)
    data = Trajectories(
        t=torch.as_tensor(t),
        x=x,
        edge_index=torch.zeros(2, 0, dtype=torch.long),
        u=u,
        meta={"state_names": ["q", "v"], "control_names": ["tau"]},
    )
    summary = noise_summary(data)
    assert set(summary) == {"q", "v", "tau"}
    assert summary["q"]["quantum"] == pytest.approx(0.003) and summary["tau"]["quantum"] == pytest.approx(0.01)
    assert summary["v"]["quantum"] is None and summary["v"]["std"] == pytest.approx(0.05, rel=0.2)
    assert summary["q"]["std"] < 0.003  # about the rounding error step/√12


def test_diagnose_uses_the_data_floors_functions():
    assert diagnose_noise.noise_level is __import__("mpsim.data.noise", fromlist=["x"]).noise_level
    assert diagnose_noise.quantisation_step is __import__("mpsim.data.noise", fromlist=["x"]).quantisation_step
