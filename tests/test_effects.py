import math

import pytest
import torch

from mpsim.effects import (
    Bias,
    CubicStiffness,
    DelayedFeedback,
    DiffusiveCoupling,
    EffectContext,
    LinearDamping,
    PeriodicForcing,
    QuadraticDrag,
    SineCoupling,
)
from mpsim.errors import ConfigError
from mpsim.graphs.topology import chain
from mpsim.systems import CoupledPendulums

NAMES = ["theta", "omega"]


def _ctx(x):
    return EffectContext.for_batch(chain(x.shape[1]), x)


def test_terms_match_their_formulas():
    x = torch.tensor([[[0.5, -2.0], [1.0, 3.0], [-1.0, 0.5]]], dtype=torch.float64)  # [1, 3, 2]
    t = torch.tensor(0.3, dtype=torch.float64)
    ctx = _ctx(x)
    w = x[..., 1]
    cases = [
        (LinearDamping(0.2, target="omega"), -0.2 * w),
        (QuadraticDrag(0.1, target="omega"), -0.1 * w * w.abs()),
        (CubicStiffness(2.0, target="omega", source="theta"), -2.0 * x[..., 0] ** 3),
        (Bias(0.7, target="omega"), torch.full_like(w, 0.7)),
        (PeriodicForcing(1.5, omega=2.0, phase=0.4, target="omega"), torch.full_like(w, 1.5 * math.sin(0.6 + 0.4))),
        (DiffusiveCoupling(1.0, target="omega"), torch.tensor([[3.0 - (-2.0), (-2.0 - 3.0) + (0.5 - 3.0), 3.0 - 0.5]])),
        (SineCoupling(1.0, target="omega", source="theta"),
         torch.tensor([[math.sin(0.5), math.sin(-0.5) + math.sin(-2.0), math.sin(2.0)]])),
    ]
    for effect, expected in cases:
        out = effect.bind(NAMES)(t, x, ctx)
        assert torch.allclose(out[..., 1], expected.to(out)), effect.name
        assert torch.all(out[..., 0] == 0), effect.name


def test_bad_names_are_clear_errors():
    with pytest.raises(ConfigError, match="'v' is not a state variable; choose one of \\['theta', 'omega'\\]"):
        LinearDamping(0.1, target="v").bind(NAMES)
    with pytest.raises(ConfigError, match="omega must be > 0"):
        PeriodicForcing(1.0, omega=0.0)


def test_hidden_damping_matches_the_damped_oscillator():
    # small angles: θ'' + c θ' + (g/l) θ = 0, solved in closed form
    c, g, l = 0.2, 9.81, 1.5
    system = CoupledPendulums(n_nodes=1, gravity=g, length=l, effects=[LinearDamping(c, target="omega")])
    th0, w0 = 1e-3, 0.0
    t = torch.linspace(0, 10, 101, dtype=torch.float64)
    traj = system.simulate(torch.tensor([[[th0, w0]]], dtype=torch.float64), t)
    wd = math.sqrt(g / l - c**2 / 4)
    exact = torch.exp(-c * t / 2) * (th0 * torch.cos(wd * t) + (w0 + c * th0 / 2) / wd * torch.sin(wd * t))
    assert torch.allclose(traj.x[0, :, 0, 0], exact, atol=1e-8)  # sin θ ≈ θ error ~ θ³ = 1e-9


def test_delayed_feedback_matches_the_method_of_steps():
    # dθ/dt = ω (declared), dω/dt = … + c·θ(t − τ); on [0, τ] the delayed term is the constant θ0
    system = CoupledPendulums(n_nodes=1, gravity=0.0, effects=[DelayedFeedback(-1.0, delay=0.5, target="omega",
                                                                               source="theta")])
    x0 = torch.tensor([[[0.3, 0.0]]], dtype=torch.float64)
    t = torch.linspace(0, 0.5, 11, dtype=torch.float64)
    traj = system.simulate(x0, t)
    assert torch.allclose(traj.x[0, :, 0, 1], -0.3 * t, atol=1e-9)  # ω = −θ0·t
    assert torch.allclose(traj.x[0, :, 0, 0], 0.3 - 0.15 * t**2, atol=1e-9)


def test_effects_are_learnable_and_serialisable():
    f = PeriodicForcing(2.0, omega=3.0, phase=0.5, target="omega").bind(NAMES)
    x = torch.zeros(1, 2, 2, dtype=torch.float64)
    f(torch.tensor(1.0), x, _ctx(x))[..., 1].sum().backward()
    assert f.coef.grad is not None and f.log_omega.grad is not None
    cfg = f.config()
    assert cfg["amplitude"] == pytest.approx(2.0) and cfg["omega"] == pytest.approx(3.0)
    assert cfg["phase"] == pytest.approx(0.5)
