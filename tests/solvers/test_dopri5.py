"""mpsim's own Dormand–Prince against torchdiffeq's (float64: the same steps and values to 1e-12) and closed forms."""

import math

import pytest
import torch
from torch import nn
from torchdiffeq import odeint

from mpsim.errors import ConfigError, DivergenceError
from mpsim.solvers import ODESolver
from mpsim.solvers.dopri5 import StepFailure, _initial_step, dopri5


class Counted(nn.Module):
    """A small tanh network as a vector field, counting its evaluations and the times it was called at."""

    def __init__(self, dim: int = 5, scale: float = 1.0, seed: int = 0):
        super().__init__()
        torch.manual_seed(seed)
        self.net = nn.Sequential(nn.Linear(dim + 1, 16), nn.Tanh(), nn.Linear(16, dim)).double()
        self.scale, self.calls, self.times = scale, 0, []

    def forward(self, t, y):  # t: [], y: [B, dim]
        self.calls += 1
        self.times.append(float(t))
        time = torch.sin(3 * t).expand(*y.shape[:-1], 1)  # a time-dependent field: stage times matter
        return self.scale * self.net(torch.cat([y, time.to(y)], dim=-1))


def _torchdiffeq(field, y0, t, rtol, atol, **options):
    return odeint(field, y0, t, rtol=rtol, atol=atol, method="dopri5", options=options or None)


@pytest.mark.parametrize(
    ("scale", "n_out", "rtol"),
    [
        (1.0, 51, 1e-4),  # several outputs per step
        (6.0, 6, 1e-8),  # several steps per output, some rejected
        (3.0, 201, 1e-6),
    ],
)
def test_same_steps_and_values_as_torchdiffeq_in_float64(scale, n_out, rtol):
    y0 = torch.randn(4, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    t = torch.linspace(0.0, 2.5, n_out, dtype=torch.float64)
    ours, theirs = Counted(scale=scale), Counted(scale=scale)
    with torch.no_grad():
        a = dopri5(ours, y0, t, rtol, rtol)
        b = _torchdiffeq(theirs, y0, t, rtol, rtol)
    assert ours.calls == theirs.calls
    assert ours.times == pytest.approx(theirs.times, rel=1e-8, abs=1e-15)
    assert torch.allclose(a, b, rtol=1e-12, atol=1e-12)


def test_backwards_in_time_as_torchdiffeq():
    y0 = torch.randn(4, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    t = torch.linspace(2.0, 0.0, 21, dtype=torch.float64)
    ours, theirs = Counted(scale=2.0), Counted(scale=2.0)
    with torch.no_grad():
        a = dopri5(ours, y0, t, 1e-7, 1e-7)
        b = _torchdiffeq(theirs, y0, t, 1e-7, 1e-7)
    assert ours.calls == theirs.calls
    assert ours.times == pytest.approx(theirs.times, rel=1e-8, abs=1e-15)
    assert torch.allclose(a, b, rtol=1e-11, atol=1e-11)


def test_steps_are_rejected_and_retried_as_torchdiffeq_does():
    """A field that turns fast after t = 1: steps grown over the quiet part are rejected there and retried shorter."""

    class Switch(nn.Module):
        def __init__(self):
            super().__init__()
            self.times = []

        def forward(self, t, y):  # y: [B, 2]
            self.times.append(float(t))
            rate = 1.0 + 400.0 * torch.sigmoid(40.0 * (t - 1.0))
            return torch.stack([y[..., 1], -rate * y[..., 0]], dim=-1)

    def retries(times):  # a retried step starts again before where the rejected one reached
        stages = times[2:]  # after the initial evaluation and the starting-step probe
        return sum(b < a for a, b in zip(stages, stages[1:], strict=False))

    y0 = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    t = torch.tensor([0.0, 2.0], dtype=torch.float64)
    ours, theirs = Switch(), Switch()
    a = dopri5(ours, y0, t, 1e-6, 1e-6)
    b = _torchdiffeq(theirs, y0, t, 1e-6, 1e-6)
    assert retries(ours.times) >= 3
    assert ours.times == pytest.approx(theirs.times, rel=1e-8, abs=1e-15)
    assert torch.allclose(a, b, rtol=1e-11, atol=1e-11)


def test_gradients_equal_torchdiffeqs_with_the_same_constant_first_step():
    """Step sizes are not differentiated: torchdiffeq given the same first step as a constant has that gradient."""
    y0 = torch.randn(3, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    t = torch.linspace(0.0, 1.5, 16, dtype=torch.float64)
    field = Counted(scale=2.0)
    with torch.no_grad():
        first = _initial_step(
            field, 0.0, y0, field(t[0], y0), 1e-7, 1e-7, lambda s: torch.tensor(s, dtype=torch.float64)
        )
    grads = []
    for solve in (
        lambda: dopri5(field, y0, t, 1e-7, 1e-7),
        lambda: _torchdiffeq(field, y0, t, 1e-7, 1e-7, first_step=first),
    ):
        field.zero_grad()
        solve().pow(2).sum().backward()
        grads.append(torch.cat([p.grad.flatten() for p in field.parameters()]))
    assert torch.allclose(grads[0], grads[1], rtol=1e-10, atol=1e-12)


def test_closed_form_oscillator_and_decay():
    t = torch.linspace(0.0, 3.0, 31, dtype=torch.float64)

    class Oscillator(nn.Module):
        def forward(self, t, y):  # y: [B, 3]: x, v of ẍ = −4x, and z of ż = −z
            return torch.stack([y[..., 1], -4.0 * y[..., 0], -y[..., 2]], dim=-1)

    ys = dopri5(Oscillator(), torch.tensor([[1.0, 0.0, 2.0]], dtype=torch.float64), t, 1e-10, 1e-10)
    exact = torch.stack([torch.cos(2 * t), -2 * torch.sin(2 * t), 2 * torch.exp(-t)], dim=-1)
    assert ys.shape == (31, 1, 3)
    assert torch.allclose(ys[:, 0], exact, atol=1e-8)


def test_float32_agrees_with_torchdiffeq_to_rounding_interval_by_interval():
    """A controlled rollout solves one sample interval at a time: 50 fresh solves chained."""
    field = Counted(scale=1.5)
    field.float()
    y0 = torch.randn(8, 5, generator=torch.Generator().manual_seed(3))
    t = torch.linspace(0.0, 2.5, 51)
    ours, theirs = [y0], [y0]
    with torch.no_grad():
        for k in range(50):
            ours.append(dopri5(field, ours[-1], t[k : k + 2], 1e-4, 1e-4)[1])
            theirs.append(_torchdiffeq(field, theirs[-1], t[k : k + 2], 1e-4, 1e-4)[1])
    assert torch.allclose(torch.stack(ours), torch.stack(theirs), rtol=1e-4, atol=1e-5)


def test_failures():
    class Blowup(nn.Module):
        def forward(self, t, y):
            return y**2  # y = 1 / (1 − t) from y0 = 1: infinite at t = 1

    y0, t = torch.ones(1, 1, dtype=torch.float64), torch.tensor([0.0, 2.0], dtype=torch.float64)
    with pytest.raises(StepFailure, match="max_num_steps"):
        dopri5(Blowup(), y0, t, 1e-6, 1e-6, max_num_steps=50)
    with pytest.raises(StepFailure, match="non-finite"):
        dopri5(Blowup(), torch.full((1, 1), math.nan, dtype=torch.float64), t, 1e-6, 1e-6)
    with pytest.raises(ValueError, match="strictly increasing or strictly decreasing"):
        dopri5(Blowup(), y0, torch.tensor([0.0, 1.0, 1.0], dtype=torch.float64), 1e-6, 1e-6)
    with pytest.raises(DivergenceError, match="stiff or blew up"):  # through ODESolver, as torchdiffeq's
        ODESolver("dopri5", max_num_steps=50)(Blowup(), y0, t)


def test_odesolver_runs_it_by_default_and_torchdiffeqs_on_request(monkeypatch):
    import mpsim.solvers.odeint as odeint_module

    used = []
    monkeypatch.setattr(odeint_module, "dopri5", lambda *a, **k: used.append(1) or dopri5(*a, **k))
    y0 = torch.randn(2, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    t = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    field = Counted()
    with torch.no_grad():
        ours = ODESolver("dopri5", rtol=1e-6, atol=1e-6)(field, y0, t)
        n_ours, field.calls = field.calls, 0
        assert used == [1]
        theirs = ODESolver("dopri5", rtol=1e-6, atol=1e-6, implementation="torchdiffeq")(field, y0, t)
        ODESolver("dopri5", adjoint=True)(field, y0, t)  # the adjoint is torchdiffeq's
        ODESolver("dopri5", stacked=False)(field, y0, t)  # as is `odeint` unstacked
    assert used == [1]
    assert ours.shape == (2, 11, 5) and n_ours > 0
    assert torch.allclose(ours, theirs, rtol=1e-12, atol=1e-12)
    with pytest.raises(ConfigError, match="implementation"):
        ODESolver("dopri5", implementation="scipy")


def test_restart_never_steps_across_an_output_and_matches_one_solve_per_interval():
    """A field whose input jumps at every output time (zero-order hold): `restart=True` ends a step on every output
    time and evaluates the field afresh there; the result is torchdiffeq's solve one interval at a time."""
    t = torch.linspace(0.0, 2.0, 41, dtype=torch.float64)
    u = torch.sin(7 * t) + torch.randn(41, generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    class Held(nn.Module):  # dy/dt = −y + u_k on [t_k, t_{k+1}): the sample at or before t
        def __init__(self):
            super().__init__()
            self.times = []

        def forward(self, s, y):
            self.times.append(float(s))
            k = int(torch.searchsorted(t, s.reshape(1), right=True)) - 1
            return -y + u[min(k, 40)]

    field, y0 = Held(), torch.tensor([[0.5], [-1.0]], dtype=torch.float64)
    got = dopri5(field, y0, t, 1e-9, 1e-11, restart=True)
    steps = [y0]
    for k in range(40):  # the reference: one solve per interval with the sample fixed (exact: e^{-h} decay to u_k)
        h = float(t[k + 1] - t[k])
        steps.append(u[k] + (steps[-1] - u[k]) * math.exp(-h))
    assert torch.allclose(got, torch.stack(steps), atol=1e-9)
    assert set(t[1:-1].tolist()) <= set(field.times)  # the field is evaluated afresh on every sample time
    plain = Held()  # without restart the steps straddle the jumps, and the tolerance shrinks them around each one
    assert torch.allclose(dopri5(plain, y0, t, 1e-9, 1e-11), got, atol=1e-6)
    assert len(field.times) < len(plain.times) / 2, (len(field.times), len(plain.times))
    with pytest.raises(ValueError, match="cannot restart"):
        ODESolver("rk4")(field, y0, t, restart=True)


class _Huge(nn.Module):
    """dy/dt = 1e30·y in float32: the derivative at the start overflows (an input sample of 1e30 did so)."""

    def forward(self, t, y):
        return y * 1e30 * 1e30


def test_a_derivative_that_overflows_at_the_start_is_a_step_failure_not_a_zero_division():
    y0 = torch.ones(2, 3)
    with pytest.raises(StepFailure, match="non-finite values in the state or its derivative at the start"):
        dopri5(_Huge(), y0, torch.tensor([0.0, 0.1]), 1e-6, 1e-8)
