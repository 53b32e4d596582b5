"""Known answers for the smoothers: a linear-Gaussian model solved densely, and nonlinear generators with an RK4
integrator of their own (fine step for the truth, a few steps per sample for the estimator's one-sample step)."""

from __future__ import annotations

import numpy as np
import torch
from scipy.stats import multivariate_normal


def exact_smoother(A, b, C, y, x0, P0, Q, R):
    """Means [T, D], marginal covariances [T, D, D] and log p(y) of one record of x_{k+1} = A x_k + b_k + w,
    y_k = C x_k + v (NaN: not measured), from the joint Gaussian over all T states solved as one dense system."""
    T, D = y.shape[0], A.shape[0]
    n = T * D
    prior_info, prior_shift = np.zeros((n, n)), np.zeros(n)

    def add(info, shift, rows, target, noise, block):  # a residual target − rows·x[block] ~ N(0, noise)
        M = np.zeros((rows.shape[0], n))
        for j, matrix in block:
            M[:, j * D : (j + 1) * D] = matrix
        W = np.linalg.inv(noise)
        info += M.T @ W @ M
        shift += M.T @ W @ target
        return M

    add(prior_info, prior_shift, np.eye(D), x0, P0, [(0, np.eye(D))])
    for k in range(T - 1):
        add(prior_info, prior_shift, np.eye(D), b[k], Q, [(k, -A), (k + 1, np.eye(D))])
    info, shift = prior_info.copy(), prior_shift.copy()
    rows, targets, noises = [], [], []
    for k in range(T):
        seen = ~np.isnan(y[k])
        if seen.any():
            rows.append(add(info, shift, C[seen], y[k, seen], R[np.ix_(seen, seen)], [(k, C[seen])]))
            targets.append(y[k, seen])
            noises.append(R[np.ix_(seen, seen)])
    cov = np.linalg.inv(info)
    mean = cov @ shift
    marginal = np.stack([cov[k * D : (k + 1) * D, k * D : (k + 1) * D] for k in range(T)])
    # log p(y): the measurements' Gaussian under the prior over the states
    prior_cov = np.linalg.inv(prior_info)
    M, target = np.concatenate(rows), np.concatenate(targets)
    noise = np.zeros((len(target), len(target)))
    i = 0
    for block in noises:
        noise[i : i + len(block), i : i + len(block)] = block
        i += len(block)
    log_likelihood = multivariate_normal(M @ prior_cov @ prior_shift, M @ prior_cov @ M.T + noise).logpdf(target)
    return mean.reshape(T, D), marginal, float(log_likelihood)


def rk4(field, x, u, dt, substeps, w=0.0):
    """x after dt of x' = field(x, u, w) with u and w held, by `substeps` classical Runge–Kutta steps (torch)."""
    h = dt / substeps
    for _ in range(substeps):
        k1 = field(x, u, w)
        k2 = field(x + h / 2 * k1, u, w)
        k3 = field(x + h / 2 * k2, u, w)
        k4 = field(x + h * k3, u, w)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


def simulate(field, x0, u, dt, substeps, w=None):
    """Trajectories [B, T, D] (float64) of x' = field(x, u, w) from x0 [B, D], the input u [B, T] and a disturbance
    w [B, T] (default 0), both held over each sample interval."""
    x = torch.as_tensor(x0, dtype=torch.float64)
    u = torch.as_tensor(u, dtype=torch.float64)
    w = torch.zeros_like(u) if w is None else torch.as_tensor(w, dtype=torch.float64)
    out = [x]
    for k in range(u.shape[1] - 1):
        x = rk4(field, x, u[:, k], dt, substeps, w[:, k])
        out.append(x)
    return torch.stack(out, dim=1)


def held_step(field, u, dt, substeps):
    """The estimator's one-sample step: x [B, R, D] at sample k -> k + 1, each record's input u [B, T] held."""
    return lambda x, k: rk4(field, x, u[:, k, None], dt, substeps)


def oscillator(omega, zeta, hardening=0.0):
    """q'' = u + w − 2ζω q' − ω² q − ε q³ (ε: `hardening`) as a field of x = (q, v); w a force the estimator is not
    told about."""

    def field(x, u, w):
        q, v = x[..., 0], x[..., 1]
        return torch.stack([v, u + w - 2 * zeta * omega * v - omega**2 * q - hardening * q**3], -1)

    return field


def tanks(a1, a2, k):
    """Two cascaded tanks (Torricelli outflow): h1' = −a1√h1 + k(u + w), h2' = a1√h1 − a2√h2 (levels clamped at 0)."""

    def field(x, u, w):
        out1 = a1 * x[..., 0].clamp(min=0).sqrt()
        return torch.stack([-out1 + k * (u + w), out1 - a2 * x[..., 1].clamp(min=0).sqrt()], -1)

    return field


def belt(alpha, omega, xi, k):
    """d' = α(k·u − d), s' = r, r' = ω²(d − s) − 2ξω·r + w, a drive with a belt's resonance; state (d, s, r)."""

    def field(x, u, w):
        d, s, r = x[..., 0], x[..., 1], x[..., 2]
        return torch.stack([alpha * (k * u - d), r, omega**2 * (d - s) - 2 * xi * omega * r + w], -1)

    return field


def multisine(n, dt, band, count, rng):
    """A multisine of `count` equal-amplitude components on the record's frequency grid within `band` (Hz),
    random phases, unit RMS, sampled at n points."""
    t = np.arange(n) * dt
    lines = np.arange(1, n // 2) / (n * dt)
    lines = lines[(lines >= band[0]) & (lines <= band[1])]
    chosen = lines[np.linspace(0, len(lines) - 1, count).round().astype(int)]
    u = np.sin(2 * np.pi * chosen[:, None] * t + rng.uniform(0, 2 * np.pi, (len(chosen), 1))).sum(0)
    return u / u.std()


def staircase(n, hold, low, high, rng):
    """A PRBS-like staircase of n samples: random levels in [low, high], each held for 1 … 2·hold samples."""
    u = np.empty(n)
    i = 0
    while i < n:
        length = int(rng.integers(1, 2 * hold + 1))
        u[i : i + length] = rng.uniform(low, high)
        i += length
    return u
