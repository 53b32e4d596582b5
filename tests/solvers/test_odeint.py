import math

import pytest
import torch
from torch import nn

from mpsim.errors import ConfigError, DivergenceError
from mpsim.solvers import ODESolver


class Oscillator(nn.Module):
    """ẍ = −ω²x: closed form x = cos ωt, v = −ω sin ωt from (1, 0)."""

    def __init__(self, omega: float = 2.0):
        super().__init__()
        self.omega = omega

    def forward(self, t, y):  # y: [B, 2]
        return torch.stack([y[..., 1], -(self.omega**2) * y[..., 0]], dim=-1)


def _exact(t, omega=2.0):
    return torch.stack([torch.cos(omega * t), -omega * torch.sin(omega * t)], dim=-1)


@pytest.mark.parametrize("method", ["dopri5", "rk4"])
def test_matches_closed_form_batch_first(method):
    t = torch.linspace(0, 3, 301, dtype=torch.float64)
    y0 = torch.tensor([[1.0, 0.0]] * 3, dtype=torch.float64)
    ys = ODESolver(method, rtol=1e-9, atol=1e-9)(Oscillator(), y0, t)
    assert ys.shape == (3, 301, 2)
    assert torch.allclose(ys[0], _exact(t), atol=1e-6)


def test_rk4_converges_at_fourth_order():
    errors = []
    for n in (20, 40, 80):
        t = torch.linspace(0, 2, n + 1, dtype=torch.float64)
        ys = ODESolver("rk4")(Oscillator(), torch.tensor([[1.0, 0.0]], dtype=torch.float64), t)
        errors.append(float((ys[0, -1] - _exact(t)[-1]).abs().max()))
    orders = [math.log2(errors[i] / errors[i + 1]) for i in range(2)]
    assert all(3.7 < p < 4.3 for p in orders), orders


def test_blow_up_is_a_divergence_error():
    class Blowup(nn.Module):
        def forward(self, t, y):
            return y**2  # y = 1 / (1 − t) from y0 = 1: infinite at t = 1

    with pytest.raises(DivergenceError, match="stiff or blew up"):
        ODESolver("dopri5", max_num_steps=200)(
            Blowup(), torch.ones(1, 1, dtype=torch.float64), torch.tensor([0.0, 2.0], dtype=torch.float64)
        )


def test_unknown_method_lists_choices():
    with pytest.raises(ConfigError, match="dopri5"):
        ODESolver("tsit5")


def test_adjoint_gradients_match_backprop():
    torch.manual_seed(0)
    net = nn.Sequential(nn.Linear(2, 8), nn.Tanh(), nn.Linear(8, 2)).double()

    class Field(nn.Module):
        def __init__(self):
            super().__init__()
            self.net = net

        def forward(self, t, y):
            return self.net(y)

    y0 = torch.randn(3, 2, dtype=torch.float64)
    t = torch.linspace(0, 1, 5, dtype=torch.float64)
    grads = []
    for adjoint in (False, True):
        net.zero_grad()
        ODESolver("dopri5", rtol=1e-9, atol=1e-9, adjoint=adjoint)(Field(), y0, t).pow(2).sum().backward()
        grads.append(torch.cat([p.grad.flatten() for p in net.parameters()]))
    assert torch.allclose(grads[0], grads[1], rtol=1e-5, atol=1e-7)


class _Field(nn.Module):  # a small learned field: dy/dt = W2 tanh(W1 y + b t)
    def __init__(self):
        super().__init__()
        torch.manual_seed(0)
        self.inner, self.outer = nn.Linear(3, 8).double(), nn.Linear(8, 3).double()

    def forward(self, t, y):
        return self.outer(torch.tanh(self.inner(y) + t))


@pytest.mark.parametrize(
    ("method", "options"),
    [(m, {}) for m in ("dopri5", "dopri8", "bosh3", "fehlberg2", "adaptive_heun")]
    + [(m, {}) for m in ("euler", "midpoint", "heun2", "heun3", "rk4", "explicit_adams", "implicit_adams")]
    + [("rk4", {"step_size": 0.07}), ("euler", {"step_size": 0.03})],
)
@pytest.mark.parametrize("reverse", [False, True])
def test_stacked_outputs_equal_torchdiffeqs_odeint_and_its_gradients(method, options, reverse):
    # ODESolver collects the outputs in a list instead of writing them into one preallocated tensor (an O(T^2)
    # copy in the backward): the same solver steps, so the same values, and the same gradients
    from torchdiffeq import odeint

    field = _Field()
    y0 = torch.randn(4, 2, 3, dtype=torch.float64)
    t = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    t = t.flip(0) if reverse else t
    # torchdiffeq's dopri5 driven step by step (mpsim's own is tests/solvers/test_dopri5.py's)
    solver = ODESolver(method, rtol=1e-6, atol=1e-6, step_size=options.get("step_size"), implementation="torchdiffeq")

    ours = solver(field, y0, t)
    field.zero_grad()
    ours.pow(2).sum().backward()
    ours_grads = [p.grad.clone() for p in field.parameters()]
    theirs = odeint(field, y0, t, rtol=1e-6, atol=1e-6, method=method, options=solver.options).movedim(0, 1)
    field.zero_grad()
    theirs.pow(2).sum().backward()

    assert ours.shape == (4, 11, 2, 3)
    assert torch.equal(ours, theirs)
    for mine, ref in zip(ours_grads, (p.grad for p in field.parameters()), strict=True):
        assert torch.allclose(mine, ref, rtol=1e-10, atol=1e-12)


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_stacked_outputs_keep_the_backward_linear_in_the_number_of_outputs():
    # torchdiffeq's preallocated output makes autograd clone the whole [T, ...] gradient once per output; stacking
    # does not: count the elements the backward copies for T outputs
    from torch.profiler import ProfilerActivity, profile

    field = _Field()
    y0 = torch.randn(64, 3, dtype=torch.float64)

    def copied(n_times):
        t = torch.linspace(0.0, 1.0, n_times, dtype=torch.float64)
        out = ODESolver("rk4")(field, y0, t)
        with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
            out.pow(2).sum().backward()
        sizes = [math.prod(s[0]) for e in prof.events() if e.name == "aten::copy_" for s in [e.input_shapes] if s]
        return sum(sizes)

    assert copied(81) < 3 * copied(41)  # quadratic growth would give 4x


def test_a_fixed_step_too_small_for_the_step_budget_is_refused_before_the_grid_is_built():
    # torchdiffeq lays out the whole fixed grid at once: step_size=1e-12 over 0.1 asked for 20 TB (an OOM message
    # that advised fewer trajectories); it is a setting, refused with the step count and a step that fits
    y0, t = torch.ones(1, 2, dtype=torch.float64), torch.tensor([0.0, 0.1, 0.2], dtype=torch.float64)
    with pytest.raises(ConfigError, match=r"step_size=1e-12 needs 1e\+11 rk4 steps .* of 0.1 .*e.g. 0.025"):
        ODESolver("rk4", step_size=1e-12)(Oscillator(), y0, t)
    with pytest.raises(ConfigError, match="step_size=0.001 needs 100 euler steps"):
        ODESolver("euler", step_size=1e-3, max_num_steps=99)(Oscillator(), y0, t)
    ys = ODESolver("euler", step_size=1e-3, max_num_steps=100)(Oscillator(), y0, t)  # exactly the budget: runs
    assert ys.shape == (1, 3, 2)
    with pytest.raises(ConfigError, match="max_num_steps must be >= 1; got 0"):
        ODESolver("rk4", max_num_steps=0)
