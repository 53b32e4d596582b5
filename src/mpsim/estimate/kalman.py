"""Kalman smoothers over a nominal model's one-sample step and output map: extended (EKF) and unscented (UKF).

Pure functions on tensors: the caller closes over each record's inputs and parameters. Every call of the step and
the output map is batched over the B records and the 2D+1 rows of a linearisation; the only Python loop is over time
(forward, then backward). The forward pass is a Kalman filter over per-sample affine approximations (see
`mpsim.estimate.linearise`); the backward pass is the Rauch–Tung–Striebel smoother. Numerics: covariances are
symmetrised after every update, every inverse is a Cholesky solve, the measurement update is in Joseph form and the
smoother's covariance recursion is written as a sum of positive semidefinite terms, so both stay positive definite.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from mpsim.errors import DataError
from mpsim.estimate.linearise import METHODS, Affine, Map, cholesky, linearise, symmetrise


@dataclass
class Smoothed:
    """A smoother's result: the states' posterior means and covariances given every measurement of the record.

    Example (`kalman_smoother`'s docstring has one that runs)::

        s = kalman_smoother(step, output, y, x0, P0, Q, R)
        s.mean[:, :, 1], s.std[:, :, 1]  # the second state and its ±1σ spread, [B, T] each
    """

    mean: Tensor  # [B, T, D]
    cov: Tensor  # [B, T, D, D]
    log_likelihood: Tensor  # [B] log p(y) of each record from the filter's innovations (under the linearisation)

    @property
    def std(self) -> Tensor:
        """[B, T, D] the marginal standard deviations."""
        return self.cov.diagonal(dim1=-2, dim2=-1).clamp_min(0).sqrt()


@dataclass
class _Filtered:
    mean: Tensor  # [B, T, D] filtered means
    cov: Tensor  # [B, T, D, D]
    slope: Tensor  # [B, T-1, D, D] the step's slope from sample k to k+1
    noise: Tensor  # [B, T-1, D, D] Q plus the step's linearisation-error covariance
    pred_mean: Tensor  # [B, T-1, D] predicted mean of sample k+1
    pred_cov: Tensor  # [B, T-1, D, D]
    log_likelihood: Tensor  # [B]


def _shift(lin: Affine, mean: Tensor) -> Tensor:
    """The affine approximation's value at `mean: [B, D]`: value + slope (mean − point) -> [B, P]."""
    if lin.point is mean:  # linearised about this very estimate (the first pass): no slope term
        return lin.value
    return lin.value + (lin.slope @ (mean - lin.point)[..., None])[..., 0]


def _update(mean: Tensor, cov: Tensor, y: Tensor, lin: Affine, R: Tensor, gaps: bool) -> tuple[Tensor, ...]:
    """Measurement update of N(mean [B, D], cov [B, D, D]) with y [B, P] (NaN: not measured, when `gaps`) and noise
    R [B, P, P]. Returns the posterior mean and covariance, and for the log-likelihood the innovation [B, P], the
    whitened innovation S⁻¹v [B, P] and the diagonal of S's Cholesky factor [B, P]."""
    H, noise = lin.slope, (R if lin.extra is None else R + lin.extra)
    innovation = y - _shift(lin, mean)
    if gaps:
        seen = ~torch.isnan(y)
        weight = seen.to(mean.dtype)  # [B, P]
        H = H * weight[..., None]  # rows of unmeasured channels zeroed
        # an unmeasured channel gets unit variance and no correlation: it drops out of the gain and the likelihood
        noise = noise * (weight[:, :, None] * weight[:, None, :]) + torch.diag_embed(1 - weight)
        innovation = torch.where(seen, innovation, torch.zeros_like(innovation))
    HP = H @ cov  # [B, P, D]
    factor = cholesky(symmetrise(HP @ H.mT + noise), "innovation covariance H P Hᵀ + R")
    gain = torch.cholesky_solve(HP, factor).mT  # [B, D, P] = P Hᵀ S⁻¹ (P symmetric)
    mean = mean + (gain @ innovation[..., None])[..., 0]
    keep = -gain @ H
    keep.diagonal(dim1=-2, dim2=-1).add_(1)  # I − K H
    cov = symmetrise(keep @ cov @ keep.mT + gain @ noise @ gain.mT)  # Joseph form
    whitened = torch.cholesky_solve(innovation[..., None], factor)[..., 0]
    return mean, cov, innovation, whitened, factor.diagonal(dim1=-2, dim2=-1)


def _log_likelihood(innovation: Tensor, whitened: Tensor, root: Tensor, y: Tensor) -> Tensor:
    """[B] Σ_k log N(v_k; 0, S_k) from innovations v [B, T, P], S⁻¹v [B, T, P] and diag chol(S) [B, T, P]; an
    unmeasured channel (NaN in y [B, T, P]) has v = 0 and unit variance, so only its 2π term is taken out."""
    measured = (~torch.isnan(y)).sum(dim=(1, 2)).to(y.dtype)
    quadratic = (innovation * whitened).sum(dim=(1, 2))
    return -0.5 * (quadratic + 2 * root.log().sum(dim=(1, 2)) + measured * math.log(2 * math.pi))


def _filter(
    step: Map, output: Map, y: Tensor, x0: Tensor, P0: Tensor, Q: Tensor, R: Tensor, method: str, path: Smoothed | None
) -> _Filtered:
    """The forward pass; linearised about the running estimate (`path` None) or about a previous smoothed path."""
    (B, T, P), D = y.shape, x0.shape[-1]
    gaps = bool(torch.isnan(y).any())
    mean, cov = x0, P0
    means, covs, slopes, noises, pred_means, pred_covs, terms = [], [], [], [], [], [], []
    for k in range(T):
        at = (mean, cov) if path is None else (path.mean[:, k], path.cov[:, k])
        mean, cov, *term = _update(mean, cov, y[:, k], linearise(output, k, *at, method, "output", P), R, gaps)
        terms.append(term)
        means.append(mean)
        covs.append(cov)
        if k == T - 1:
            break
        at = (mean, cov) if path is None else (path.mean[:, k], path.cov[:, k])
        lin = linearise(step, k, *at, method, "step", D)
        noise = Q if lin.extra is None else Q + lin.extra
        mean = _shift(lin, mean)
        cov = symmetrise(lin.slope @ cov @ lin.slope.mT + noise)
        slopes.append(lin.slope)
        noises.append(noise.expand_as(cov))
        pred_means.append(mean)
        pred_covs.append(cov)
    empty = x0.new_zeros(B, 0, D, D)
    innovation, whitened, root = (torch.stack(parts, dim=1) for parts in zip(*terms, strict=True))
    stack = lambda items, blank: torch.stack(items, dim=1) if items else blank  # noqa: E731
    return _Filtered(
        mean=torch.stack(means, dim=1),
        cov=torch.stack(covs, dim=1),
        slope=stack(slopes, empty),
        noise=stack(noises, empty),
        pred_mean=stack(pred_means, x0.new_zeros(B, 0, D)),
        pred_cov=stack(pred_covs, empty),
        log_likelihood=_log_likelihood(innovation, whitened, root, y),
    )


def _smooth(f: _Filtered) -> Smoothed:
    """Rauch–Tung–Striebel backward pass. The gains and the parts of the covariance recursion that do not depend on
    the later smoothed values are computed for all samples at once; the loop over time only chains them."""
    T = f.mean.shape[1]
    # G_k = P_k Fᵀ (P⁻_{k+1})⁻¹; P^s_k = (I − G F) P_k (I − G F)ᵀ + G N Gᵀ + G P^s_{k+1} Gᵀ (= P_k + G(P^s − P⁻)Gᵀ)
    gain = torch.cholesky_solve(f.slope @ f.cov[:, :-1], cholesky(f.pred_cov, "predicted covariance")).mT
    eye = torch.eye(f.mean.shape[-1], dtype=f.mean.dtype, device=f.mean.device)
    keep = eye - gain @ f.slope
    fixed = keep @ f.cov[:, :-1] @ keep.mT + gain @ f.noise @ gain.mT  # [B, T-1, D, D]
    shift = f.mean[:, :-1] - (gain @ f.pred_mean[..., None])[..., 0]  # [B, T-1, D]
    means, covs = [f.mean[:, -1]], [f.cov[:, -1]]
    for k in range(T - 2, -1, -1):
        G = gain[:, k]
        means.append(shift[:, k] + (G @ means[-1][..., None])[..., 0])
        covs.append(symmetrise(fixed[:, k] + G @ covs[-1] @ G.mT))
    return Smoothed(
        mean=torch.stack(means[::-1], dim=1), cov=torch.stack(covs[::-1], dim=1), log_likelihood=f.log_likelihood
    )


def _batched(name: str, a: Tensor, B: int, n: int, like: Tensor) -> Tensor:
    """`a` as [B, n, n] in `like`'s dtype and device (a [n, n] is shared by every record)."""
    a = torch.as_tensor(a).to(dtype=like.dtype, device=like.device)
    if a.shape not in ((n, n), (B, n, n)):
        raise DataError(f"{name} must be [{n}, {n}] or [{B}, {n}, {n}] (got {tuple(a.shape)}).")
    return symmetrise(a.expand(B, n, n))


def _checked(
    y: Tensor, x0: Tensor, P0: Tensor, Q: Tensor, R: Tensor, method: str, iterations: int
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The arguments in one floating dtype (x0's) with a batch dimension each; a clear message otherwise."""
    if method not in METHODS:
        raise DataError(f"method must be one of {METHODS} (got {method!r}).")
    if iterations < 1:
        raise DataError(f"iterations must be at least 1 (got {iterations}).")
    if not x0.is_floating_point() or x0.dim() != 2:
        raise DataError(f"x0 must be a floating tensor [B, D] (got {x0.dtype} of shape {tuple(x0.shape)}).")
    B, D = x0.shape
    y = torch.as_tensor(y).to(dtype=x0.dtype, device=x0.device)
    if y.dim() != 3 or y.shape[0] != B or y.shape[1] < 1:
        raise DataError(f"y must be [B, T, P] with B = {B} records (x0's) and T ≥ 1 (got {tuple(y.shape)}).")
    P = y.shape[-1]
    return y, _batched("P0", P0, B, D, x0), _batched("Q", Q, B, D, x0), _batched("R", R, B, P, x0)


def kalman_smoother(
    step: Map,
    output: Map,
    y: Tensor,
    x0: Tensor,
    P0: Tensor,
    Q: Tensor,
    R: Tensor,
    method: str = "ekf",
    iterations: int = 1,
) -> Smoothed:
    """Smoothed states of B records from their measured outputs, over a nominal model x_{k+1} = step(x_k) + w,
    y_k = output(x_k) + v, with w ~ N(0, Q), v ~ N(0, R) and x_0 ~ N(x0, P0).

    Each map is called with a batch of states x [B, R, D] (R rows per record: the estimate and the points about it)
    and the sample index k; it broadcasts each record's inputs over the R rows. The step takes sample k to k + 1
    (k = 0 … T−2); the output is what the sensors read at sample k (k = 0 … T−1).

    Args:
        step: x [B, R, D] at sample k -> x [B, R, D] at sample k + 1.
        output: x [B, R, D] at sample k -> y [B, R, P].
        y: [B, T, P] measured outputs; NaN where a channel was not measured at a sample (its update is skipped).
        x0: [B, D] prior mean of the first state; its dtype (float32 or float64) and device are used throughout.
        P0: [B, D, D] or [D, D] prior covariance of the first state.
        Q: [D, D] or [B, D, D] process noise covariance added per step.
        R: [P, P] or [B, P, P] measurement noise covariance.
        method: "ekf" (Jacobians by central differences) or "ukf" (unscented, sigma points); both call each map on
            2D + 1 rows per record and sample.
        iterations: passes; each pass after the first linearises about the previous smoothed path (its means, and
            for the UKF its covariances too: an iterated posterior-linearisation smoother). 1 for a plain smoother.

    Returns:
        `Smoothed` with mean [B, T, D], cov [B, T, D, D] and log_likelihood [B] (of the last pass).

    Raises:
        DataError: a shape, dtype or option is wrong (the message names it).
        DivergenceError: a map returned NaN/inf, or a covariance lost positive definiteness.

    Example:
        >>> A = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=torch.float64)
        >>> step = lambda x, k: x @ A.mT
        >>> output = lambda x, k: x[..., :1]
        >>> y = torch.randn(4, 50, 1, dtype=torch.float64)
        >>> s = kalman_smoother(step, output, y, torch.zeros(4, 2, dtype=torch.float64),
        ...                     torch.eye(2), 1e-3 * torch.eye(2), 0.1 * torch.eye(1))
        >>> s.mean.shape, s.cov.shape, s.log_likelihood.shape
        (torch.Size([4, 50, 2]), torch.Size([4, 50, 2, 2]), torch.Size([4]))
    """
    y, P0, Q, R = _checked(y, x0, P0, Q, R, method, iterations)
    path = None
    for _ in range(iterations):
        path = _smooth(_filter(step, output, y, x0, P0, Q, R, method, path))
    assert path is not None
    return path
