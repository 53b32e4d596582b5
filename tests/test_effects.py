import math

import pytest
import torch

from mpsim.effects import (
    Bias,
    CosineCoupling,
    CubicStiffness,
    DelayedFeedback,
    DiffusiveCoupling,
    DryFriction,
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
        (
            SineCoupling(1.0, target="omega", source="theta"),
            torch.tensor([[math.sin(0.5), math.sin(-0.5) + math.sin(-2.0), math.sin(2.0)]]),
        ),
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
    system = CoupledPendulums(
        n_nodes=1, gravity=0.0, effects=[DelayedFeedback(-1.0, delay=0.5, target="omega", source="theta")]
    )
    x0 = torch.tensor([[[0.3, 0.0]]], dtype=torch.float64)
    t = torch.linspace(0, 0.5, 11, dtype=torch.float64)
    traj = system.simulate(x0, t)
    assert torch.allclose(traj.x[0, :, 0, 1], -0.3 * t, atol=1e-9)  # ω = −θ0·t
    assert torch.allclose(traj.x[0, :, 0, 0], 0.3 - 0.15 * t**2, atol=1e-9)


def test_effects_are_learnable_and_serialisable():
    f = PeriodicForcing(2.0, omega=3.0, phase=0.5, target="omega").bind(NAMES)
    x = torch.zeros(1, 2, 2, dtype=torch.float64)
    f(torch.tensor(1.0), x, _ctx(x))[..., 1].sum().backward()
    assert float(f.coef.grad.abs().sum()) > 0 and float(f.log_omega.grad.abs().sum()) > 0  # both reach the output
    cfg = f.config()
    assert cfg["amplitude"] == pytest.approx(2.0) and cfg["omega"] == pytest.approx(3.0)
    assert cfg["phase"] == pytest.approx(0.5)


def test_dry_friction_and_cosine_coupling_match_their_formulas():
    x = torch.tensor([[[0.5, -0.02], [1.0, 0.003], [-1.0, 0.5]]], dtype=torch.float64)  # [1, 3, 2]
    t, ctx = torch.tensor(0.0, dtype=torch.float64), _ctx(x)
    w, th = x[0, :, 1].tolist(), x[0, :, 0].tolist()
    dry = DryFriction(0.5, target="omega", scale=0.01).bind(NAMES)(t, x, ctx)[0, :, 1]
    assert torch.allclose(dry, torch.tensor([-0.5 * math.tanh(v / 0.01) for v in w], dtype=torch.float64))
    # chain 0-1-2: node 0 hears 1, node 1 hears 0 and 2, node 2 hears 1
    cos = CosineCoupling(0.7, target="omega", source="theta").bind(NAMES)(t, x, ctx)
    expected = [
        0.7 * math.cos(th[1] - th[0]),
        0.7 * (math.cos(th[0] - th[1]) + math.cos(th[2] - th[1])),
        0.7 * math.cos(th[1] - th[2]),
    ]
    assert torch.allclose(cos[0, :, 1], torch.tensor(expected, dtype=torch.float64))
    assert torch.all(cos[..., 0] == 0)


def test_sine_and_cosine_coupling_express_a_phase_lag():
    k, alpha = 1.3, 0.25
    x = torch.randn(4, 5, 1, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    ctx = EffectContext.for_batch(chain(5), x)
    pair = SineCoupling(k * math.cos(alpha), target=0)(0.0, x, ctx) + CosineCoupling(-k * math.sin(alpha), target=0)(
        0.0, x, ctx
    )
    s = x[..., 0]
    lag = torch.zeros_like(s)
    lag[:, 1:] += torch.sin(s[:, :-1] - s[:, 1:] - alpha)  # from the left neighbour
    lag[:, :-1] += torch.sin(s[:, 1:] - s[:, :-1] - alpha)  # from the right neighbour
    assert torch.allclose(pair[..., 0], k * lag)


def test_new_effects_round_trip_through_their_config():
    from hydra.utils import instantiate

    effects = [
        DryFriction(0.5, target="omega", scale=1e-3, learnable=False),
        CosineCoupling(-0.3, target="omega", source="theta"),
        PeriodicForcing(1.5, omega=3.1, phase=0.2, target="omega", random_phase=True, phase_seed=7),
    ]
    x = torch.randn(3, 3, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    t = torch.tensor(0.8, dtype=torch.float64)
    for effect in effects:
        effect.bind(NAMES)
        cfg = effect.config()
        rebuilt = instantiate(cfg).bind(NAMES)
        again = rebuilt.config()
        assert type(rebuilt) is type(effect) and again.keys() == cfg.keys()
        assert all(again[k] == pytest.approx(v) if isinstance(v, float) else again[k] == v for k, v in cfg.items())
        assert torch.allclose(rebuilt(t, x, _ctx(x)), effect(t, x, _ctx(x))), effect.name
    assert effects[0].config()["scale"] == 1e-3
    plain = PeriodicForcing(1.0, omega=2.0, target="omega").bind(NAMES).config()
    assert "random_phase" not in plain and "phase_seed" not in plain  # the existing shape, unchanged
    assert set(plain) == {"_target_", "target", "amplitude", "omega", "phase"}


def test_random_phase_forcing_differs_per_trajectory_and_is_reproducible():
    a, w, phi = 1.5, 3.1, 0.4
    x = torch.zeros(6, 2, 2, dtype=torch.float64)
    t = torch.tensor(0.7, dtype=torch.float64)
    f = PeriodicForcing(a, omega=w, phase=phi, target="omega", random_phase=True, phase_seed=3).bind(NAMES)
    phases = 2 * math.pi * torch.rand(6, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    out = f(t, x, _ctx(x)).detach()[..., 1]  # [6, 2]
    assert torch.allclose(out, (a * torch.sin(w * 0.7 + phi + phases))[:, None].expand(6, 2))
    assert len({round(float(v), 6) for v in out[:, 0]}) == 6  # one drive per trajectory, shared across its nodes
    again = PeriodicForcing(a, omega=w, phase=phi, target="omega", random_phase=True, phase_seed=3).bind(NAMES)
    assert torch.equal(again(t, x, _ctx(x)), f(t, x, _ctx(x)))
    other = PeriodicForcing(a, omega=w, phase=phi, target="omega", random_phase=True, phase_seed=4).bind(NAMES)
    assert not torch.allclose(other(t, x, _ctx(x)), f(t, x, _ctx(x)))
    shared = PeriodicForcing(a, omega=w, phase=phi, target="omega").bind(NAMES)(t, x, _ctx(x))[..., 1]
    assert torch.allclose(shared, torch.full_like(shared, a * math.sin(w * 0.7 + phi)))


def test_new_effects_refuse_bad_arguments():
    with pytest.raises(ConfigError, match="DryFriction.scale must be a finite number > 0"):
        DryFriction(0.5, target="omega", scale=0.0)
    with pytest.raises(ConfigError, match="random_phase must be true or false"):
        PeriodicForcing(1.0, random_phase="yes")
    with pytest.raises(ConfigError, match="phase_seed must be an integer >= 0"):
        PeriodicForcing(1.0, random_phase=True, phase_seed=-1)
