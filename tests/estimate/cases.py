"""The three nonlinear cases of tests/estimate/test_latent_states.py, each as B records (own input, own noise):
the truth from a fine RK4 (10 or 20 steps a sample), the estimator's step a coarse RK4 (4 or 2 steps a sample), the
input held over each sample (as a DAC plays it), and a disturbance held per sample that the estimator is not told of
(only its variance, as Q). `python -m tests.estimate.cases` prints every figure that docs/estimation.md quotes."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cache

import numpy as np
import torch
from scipy.signal import savgol_filter

from mpsim.estimate import Smoothed, kalman_smoother
from tests.estimate.oracles import belt, held_step, multisine, oscillator, simulate, staircase, tanks

F64 = torch.float64


@dataclass
class Case:
    """A batch of records with their truth and the smoother's arguments."""

    truth: torch.Tensor  # [B, T, D]
    y: torch.Tensor  # [B, T, P]
    step: object
    output: object
    x0: torch.Tensor  # [B, D]
    P0: torch.Tensor  # [D, D]
    Q: torch.Tensor  # [D, D]
    R: torch.Tensor  # [P, P]
    extra: dict = field(default_factory=dict)

    def smooth(self, method: str = "ekf", iterations: int = 1, dtype=F64) -> Smoothed:
        cast = lambda a: a.to(dtype)  # noqa: E731
        args = (cast(self.y), cast(self.x0), cast(self.P0), cast(self.Q), cast(self.R))
        step, output = self.step, self.output
        if dtype != F64:  # the maps close over float64 inputs: run them in the smoother's dtype
            step = lambda x, k: self.step(x.to(F64), k).to(dtype)  # noqa: E731
            output = lambda x, k: self.output(x.to(F64), k).to(dtype)  # noqa: E731
        return kalman_smoother(step, output, *args, method=method, iterations=iterations)


def rmse(estimate, truth):
    """[B] root mean square over time of estimate − truth ([B, T] each)."""
    return (torch.as_tensor(estimate) - truth).pow(2).mean(-1).sqrt()


def held_noise(sigma, gain):
    """Q [D, D] of a white disturbance of std `sigma` held over a sample and entering through `gain` (the state's change
    per unit disturbance over dt), with a small floor on the diagonal so that Q is positive definite."""
    gain = torch.as_tensor(gain, dtype=F64)
    Q = sigma**2 * torch.outer(gain, gain)
    return Q + 1e-6 * Q.diagonal().max() * torch.eye(len(gain), dtype=F64)


@cache  # built once per process: the ekf and ukf tests share it
def oscillator_case(records=4, seed=0, hardening=0.0, noise=0.02, force=0.3):
    """q'' = u + w − 2ζω q' − ω² q − ε q³, ω = 2π (1 Hz), ζ = 0.1, sampled at 8.5 samples a period (dt = 1/8.5 s),
    400 samples; u a multisine of 20 lines in 0.05–1.5 Hz (RMS ω²), w white of std force·ω², q measured with noise of
    `noise` times q's std. The Savitzky–Golay velocity (5 samples, order 2) is in extra["savgol"]."""
    omega, zeta, dt, n = 2 * math.pi, 0.1, 1 / 8.5, 400
    rng = np.random.default_rng(seed)
    u = torch.as_tensor(np.stack([multisine(n, dt, (0.05, 1.5), 20, rng) for _ in range(records)]) * omega**2)
    sigma_w = force * omega**2
    law = oscillator(omega, zeta, hardening)
    truth = simulate(law, torch.zeros(records, 2), u, dt, 20, sigma_w * rng.standard_normal((records, n)))
    sigma = noise * float(truth[..., 0].std())
    y = truth[..., :1] + sigma * torch.as_tensor(rng.standard_normal((records, n, 1)))
    x0 = torch.stack([y[:, 0, 0], torch.zeros(records, dtype=F64)], -1)
    savgol = torch.as_tensor(savgol_filter(y[..., 0].numpy(), 5, 2, deriv=1, delta=dt, axis=-1))
    return Case(
        truth=truth,
        y=y,
        step=held_step(law, u, dt, 4),
        output=lambda x, k: x[..., :1],
        x0=x0,
        P0=torch.diag(torch.tensor([sigma, 50.0], dtype=F64) ** 2),
        Q=held_noise(sigma_w, [dt**2 / 2, dt]),
        R=torch.tensor([[sigma**2]], dtype=F64),
        extra={"savgol": savgol},
    )


@cache  # built once per process: the ekf and ukf tests share it
def tanks_case(records=4, seed=0, noise=0.05, inflow=0.05):
    """Two cascaded tanks h1' = −a1√h1 + k(u + w), h2' = a1√h1 − a2√h2 with a1 = 0.5, a2 = 0.4, k = 1, dt = 1 s,
    300 samples; u a staircase of levels in [0.1, 1] held 1–40 samples, w white of std `inflow`; starts uniform in
    [0.5, 3]; h2 measured with noise of std `noise`. extra["inversion"]: h1 from h2 by inverting the second equation,
    h1 = ((h2' + a2√h2)/a1)², with h2 and h2' from a 5-sample Savitzky–Golay filter (order 2)."""
    a1, a2, k, dt, n = 0.5, 0.4, 1.0, 1.0, 300
    rng = np.random.default_rng(seed)
    u = torch.as_tensor(np.stack([staircase(n, 20, 0.1, 1.0, rng) for _ in range(records)]))
    law = tanks(a1, a2, k)
    start = torch.as_tensor(rng.uniform(0.5, 3.0, (records, 2)))
    truth = simulate(law, start, u, dt, 10, inflow * rng.standard_normal((records, n)))
    y = truth[..., 1:] + noise * torch.as_tensor(rng.standard_normal((records, n, 1)))
    level = savgol_filter(y[..., 0].numpy(), 5, 2, axis=-1)
    slope = savgol_filter(y[..., 0].numpy(), 5, 2, deriv=1, delta=dt, axis=-1)
    inversion = torch.as_tensor(((slope + a2 * np.sqrt(level.clip(0))) / a1).clip(0) ** 2)
    return Case(
        truth=truth,
        y=y,
        step=held_step(law, u, dt, 4),
        output=lambda x, k: x[..., 1:],
        x0=y[:, 0].expand(records, 2).clone(),
        P0=torch.diag(torch.tensor([2.0, noise], dtype=F64) ** 2),
        Q=held_noise(inflow, [k * dt, 0.1 * k * dt]),  # h2 gains ≈ a1/(4√h1)·dt of h1's change
        R=torch.tensor([[noise**2]], dtype=F64),
        extra={"inversion": inversion},
    )


@cache  # built once per process: the ekf and ukf tests share it
def belt_case(records=4, seed=0, noise=0.05, torque=100.0):
    """d' = α(k·u − d), s' = r, r' = ω²(d − s) − 2ξω·r + w with α = 6.7, ω = 20.5, ξ = 0.32, k = 1.8, 50 Hz, 500
    samples; u a staircase of levels in [−1, 1] held 1–20 samples, w white of std `torque`; starts at rest; the sensor
    reads |s| with noise of std `noise`. extra["simulation"]: s simulated from u alone (the nominal model from rest);
    extra["signed"]: the sensor's |s| given the simulation's sign."""
    alpha, omega, xi, k, dt, n = 6.7, 20.5, 0.32, 1.8, 0.02, 500
    rng = np.random.default_rng(seed)
    u = torch.as_tensor(np.stack([staircase(n, 10, -1.0, 1.0, rng) for _ in range(records)]))
    law = belt(alpha, omega, xi, k)
    truth = simulate(law, torch.zeros(records, 3), u, dt, 10, torque * rng.standard_normal((records, n)))
    y = truth[..., 1:2].abs() + noise * torch.as_tensor(rng.standard_normal((records, n, 1)))
    simulation = simulate(law, torch.zeros(records, 3), u, dt, 2)[..., 1]
    return Case(
        truth=truth,
        y=y,
        step=held_step(law, u, dt, 2),
        output=lambda x, k: x[..., 1:2].abs(),
        x0=torch.zeros(records, 3, dtype=F64),
        P0=torch.diag(torch.tensor([1.0, 1.0, 10.0], dtype=F64) ** 2),
        Q=held_noise(torque, [0.0, dt**2 / 2, dt]),
        R=torch.tensor([[noise**2]], dtype=F64),
        extra={"simulation": simulation, "signed": y[..., 0] * torch.sign(simulation), "noise": noise},
    )


def sign_agreement(estimate, truth, noise):
    """[B] the fraction of samples, among those with |s| > 3·noise, where the estimate has the truth's sign."""
    clear = truth.abs() > 3 * noise
    agree = (torch.sign(torch.as_tensor(estimate)) == torch.sign(truth)) & clear
    return agree.sum(-1) / clear.sum(-1)


def coverage(smoothed: Smoothed, truth, index):
    """[B] the fraction of samples where state `index` lies within ±2σ of the smoothed mean."""
    error = (smoothed.mean[..., index] - truth[..., index]).abs()
    return (error <= 2 * smoothed.std[..., index]).to(F64).mean(-1)


def _span(values) -> str:
    """'min–max' of a tensor of per-record figures."""
    return f"{float(values.min()):.3g}–{float(values.max()):.3g}"


def main(seeds=(0, 1, 2, 3)) -> None:
    """Every figure of docs/estimation.md's table: per case and method, the range over 4 seeds × 4 records."""
    runs = [("ekf", 1), ("ukf", 1), ("ukf", 3)]
    builders = [
        ("oscillator, velocity", lambda s: oscillator_case(seed=s), 1, "savgol", "Savitzky–Golay"),
        (
            "oscillator ε = 20, velocity",
            lambda s: oscillator_case(seed=s, hardening=20.0),
            1,
            "savgol",
            "Savitzky–Golay",
        ),
        ("tanks, h1", lambda s: tanks_case(seed=s), 0, "inversion", "inversion + S–G"),
        ("belt |s|, s", lambda s: belt_case(seed=s), 1, "signed", "|y|·sign(simulation)"),
    ]
    for title, build, index, naive, naive_name in builders:
        cases = [build(s) for s in seeds]
        truth = torch.cat([c.truth[..., index] for c in cases])
        spread = truth.std(-1)
        naive_all = torch.cat([c.extra[naive] for c in cases])
        naive_error, naive_late = rmse(naive_all, truth), rmse(naive_all[:, 50:], truth[:, 50:])
        print(f"{title}: {len(truth)} records; {naive_name} RMSE / spread {_span(naive_error / spread)}")
        if "simulation" in cases[0].extra:
            simulated = torch.cat([rmse(c.extra["simulation"], c.truth[..., 1]) for c in cases])
            print(f"  simulation from the input RMSE / spread {_span(simulated / spread)}")
        for method, iterations in runs:
            smoothed = [c.smooth(method, iterations) for c in cases]
            mean = torch.cat([s.mean[..., index] for s in smoothed])
            error = rmse(mean, truth)
            late = rmse(mean[:, 50:], truth[:, 50:])
            cover = torch.cat([coverage(s, c.truth, index) for s, c in zip(smoothed, cases, strict=True)])
            line = (
                f"  {method} ×{iterations}: RMSE / spread {_span(error / spread)} (after sample 50: "
                f"{_span(late / truth[:, 50:].std(-1))}), RMSE / naive {_span(error / naive_error)} (after sample 50: "
                f"{_span(late / naive_late)}), worse than naive in {int((error > naive_error).sum())}, "
                f"±2σ {_span(cover)}"
            )
            if "noise" in cases[0].extra:
                line += f", sign right {_span(sign_agreement(mean, truth, cases[0].extra['noise']))}"
            print(line)


if __name__ == "__main__":
    torch.set_num_threads(1)
    main()
