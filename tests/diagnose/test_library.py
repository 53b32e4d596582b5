import math

import torch

from mpsim.diagnose.library import build_library, delayed, dominant_frequency, refine_frequency
from mpsim.systems import CoupledPendulums


def test_delayed_shift_keeps_a_constant_history():
    x = torch.arange(5.0).reshape(1, 5, 1, 1)
    assert delayed(x, 2)[0, :, 0, 0].tolist() == [0.0, 0.0, 0.0, 1.0, 2.0]


def test_library_columns_are_step_averaged_basis_functions():
    data = CoupledPendulums().generate(3, seed=0, horizon=6)
    lib = build_library(data, omegas={1: 2.0}, delays=[0.2], kinds=("LinearDamping", "PeriodicForcing",
                                                                     "DelayedFeedback", "SineCoupling"))
    kinds = [c.kind for c in lib]
    assert kinds.count("LinearDamping") == 2 and kinds.count("PeriodicForcing") == 1
    damping_w = next(c for c in lib if c.kind == "LinearDamping" and c.source == 1)
    w = data.x[..., 1:2]
    assert torch.allclose(damping_w.features, -0.5 * (w[:, 1:] + w[:, :-1]))
    forcing = next(c for c in lib if c.kind == "PeriodicForcing")
    s = torch.sin(2.0 * data.t)
    assert torch.allclose(forcing.features[0, :, 0, 0], 0.5 * (s[1:] + s[:-1]))
    assert next(c for c in lib if c.kind == "DelayedFeedback").params["delay"] == 0.2


def test_periodogram_and_refinement_find_the_drive_frequency():
    t = torch.arange(60, dtype=torch.float64) * 0.05
    omega = 7.3
    g = torch.Generator().manual_seed(0)
    r = 2.0 * torch.sin(omega * t)[None, :, None] + 0.5 * torch.randn(16, 60, 2, generator=g, dtype=torch.float64)
    w0, freqs, power = dominant_frequency(r, t)
    assert abs(w0 - omega) < 2 * math.pi / 3.0  # within a frequency bin of the 3 s record
    w = refine_frequency(r.mean(dim=(0, 2)), t, w0, 2 * math.pi / 3.0)
    assert abs(w - omega) / omega < 0.01
