"""Resolution of recorded variables: the smoothing scale of dry friction comes from the data."""

import torch

from mpsim.diagnose.noise import MAX_RESOLUTION, MIN_RESOLUTION, noise_level, quantisation_step, resolution


def _smooth(b=8, t=200, dt=0.05):  # [B, T, 1, 1] sinusoids of several phases, unit-ish spread
    time = torch.arange(t, dtype=torch.float64) * dt
    phase = torch.linspace(0, 3, b, dtype=torch.float64)[:, None]
    return torch.sin(1.3 * time[None] + phase)[..., None, None]


def test_resolution_of_clean_continuous_data_is_the_floor():
    x = _smooth()
    spread = float(x.std())
    assert abs(float(resolution(x)[0]) - MIN_RESOLUTION * spread) < 1e-12


def test_resolution_of_quantised_data_is_the_grid_step():
    step = 0.02
    x = torch.round(_smooth() / step) * step
    assert abs(float(quantisation_step(x)[0]) - step) < 1e-9
    assert abs(float(resolution(x)[0]) - max(step, float(noise_level(x)[0]))) < 1e-12
    assert float(resolution(x)[0]) >= step - 1e-9


def test_resolution_of_noisy_data_follows_the_noise_level():
    gen = torch.Generator().manual_seed(0)
    x = _smooth() + 0.01 * torch.randn(_smooth().shape, generator=gen, dtype=torch.float64)
    eps = float(resolution(x)[0])
    assert 0.008 < eps < 0.013, eps  # the noise level, not the 1e-3 floor


def test_resolution_is_capped_so_friction_stays_a_sign():
    gen = torch.Generator().manual_seed(1)
    x = torch.randn((8, 200, 1, 1), generator=gen, dtype=torch.float64)  # all noise
    assert abs(float(resolution(x)[0]) - MAX_RESOLUTION * float(x.std())) < 1e-9
