"""Affine approximations of a batched map about a Gaussian: central differences (EKF) or sigma points (UKF).

Both evaluate the map once, on 2D+1 rows per record: the centre and the centre ± a step along D directions.
The EKF steps along the coordinate axes by a small relative step and keeps the slope only (a Jacobian by central
differences). The UKF steps ± √D along the columns of the covariance's Cholesky factor (the unscented transform
with α = 1, β = 2, κ = 0: sigma-point weights 1/(2D), the centre weighted 0 in the mean and β in the covariance);
the slope through those points is the statistical linear regression of the map on the Gaussian, and what the
slope leaves unexplained is returned as an extra covariance. All weights are non-negative, so that covariance is
positive semidefinite by construction, and an affine-Gaussian filter fed with it reproduces the unscented
Kalman filter and its Rauch–Tung–Striebel smoother exactly.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from mpsim.errors import DataError, DivergenceError

Map = Callable[[Tensor, int], Tensor]
METHODS = ("ekf", "ukf")
UKF_BETA = 2.0  # the centre's weight in the unscented covariance (2 is exact for a Gaussian's fourth moment)


@dataclass
class Affine:
    """fn(x) ≈ value + slope (x − point), with `extra` the covariance of what the slope leaves out (UKF only)."""

    point: Tensor  # [B, D] where the map was linearised
    value: Tensor  # [B, P] the map's mean there (EKF: its value)
    slope: Tensor  # [B, P, D]
    extra: Tensor | None  # [B, P, P] linearisation-error covariance (None for the EKF)


def symmetrise(a: Tensor) -> Tensor:
    """(a + aᵀ)/2 over the last two dimensions (`a: [..., D, D]`)."""
    return 0.5 * (a + a.mT)


def cholesky(a: Tensor, what: str) -> Tensor:
    """Lower Cholesky factor of the symmetric positive definite `a: [..., D, D]`; a matrix that round-off has left
    barely indefinite gets a growing diagonal jitter (up to 1e-6 of its mean diagonal) before giving up."""
    factor, info = torch.linalg.cholesky_ex(a)
    if not bool((info > 0).any()):
        return factor
    scale = a.diagonal(dim1=-2, dim2=-1).abs().mean(-1, keepdim=True).clamp_min(torch.finfo(a.dtype).tiny)
    eye = torch.eye(a.shape[-1], dtype=a.dtype, device=a.device)
    for exponent in (-12, -10, -8, -6):
        jitter = (scale * 10.0**exponent)[..., None] * eye
        factor, info = torch.linalg.cholesky_ex(a + jitter)
        if not bool((info > 0).any()):
            return factor
    raise DivergenceError(
        f"The {what} is not positive definite (its Cholesky factorisation fails even with a diagonal jitter of "
        "1e-6 of its mean diagonal). Check that R and Q (or P0) are positive definite and that the step and output "
        "functions return finite values; a float32 run with widely different state scales may need float64."
    )


def _evaluate(fn: Map, rows: Tensor, k: int, what: str, width: int) -> Tensor:
    """fn on `rows: [B, R, D]` at sample k, its result checked to be [B, R, width]."""
    out = fn(rows, k)
    if not isinstance(out, Tensor) or out.shape != (*rows.shape[:2], width):
        got = tuple(out.shape) if isinstance(out, Tensor) else type(out).__name__
        raise DataError(
            f"The {what} function must map x [B, R, D] = {tuple(rows.shape)} to a tensor [B, R, {width}] with the "
            f"same B and R (got {got} at sample {k}). Let it broadcast each record's inputs over the R rows"
            + (" and return the whole state." if what == "step" else "; y [B, T, P] sets P.")
        )
    return out.to(rows.dtype)


def linearise(fn: Map, k: int, mean: Tensor, cov: Tensor, method: str, what: str, width: int) -> Affine:
    """Affine approximation of `fn(·, k)` about N(mean, cov), by `method` ("ekf" or "ukf"), in one call of `fn`.

    Args:
        fn: the map, x [B, R, D] -> [B, R, P].
        k: the sample index passed to `fn`.
        mean: [B, D] the Gaussian's mean (the linearisation point).
        cov: [B, D, D] its covariance (EKF: scales the difference step; UKF: places the sigma points).
        method: "ekf" or "ukf".
        what: the map's name for error messages ("step" or "output").
        width: the size P of the map's result (checked).

    Returns:
        An `Affine` with value [B, P], slope [B, P, D] and (UKF) extra [B, P, P].
    """
    dim = mean.shape[-1]
    if method == "ekf":
        # a central difference's error is O(h²) from curvature and O(eps/h) from round-off: h ∝ eps^(1/3), relative
        # to the state's size or its spread, whichever is larger
        spread = cov.diagonal(dim1=-2, dim2=-1).clamp_min(0).sqrt()
        h = (torch.finfo(mean.dtype).eps ** (1 / 3) * (mean.abs() + spread)).clamp_min(torch.finfo(mean.dtype).eps)
        offsets = torch.diag_embed(h)  # [B, D, D] row i: step along axis i
    else:
        factor = cholesky(symmetrise(cov), f"covariance the {what} function is linearised over")
        offsets = math.sqrt(dim) * factor.mT  # [B, D, D] row i: √D times the factor's column i
    rows = torch.cat([mean[:, None], mean[:, None] + offsets, mean[:, None] - offsets], dim=1)  # [B, 2D+1, D]
    out = _evaluate(fn, rows, k, what, width)
    centre, plus, minus = out[:, 0], out[:, 1 : dim + 1], out[:, dim + 1 :]
    if not bool(torch.isfinite(out).all()):
        raise DivergenceError(
            f"The {what} function returned NaN or inf at sample {k} (on the estimate or a step away from it). Make "
            "it finite for states near the estimate (clamp a square root's argument, say), or give smaller Q and P0."
        )
    difference = (plus - minus).mT / 2  # [B, P, D] column i: half the change along direction i
    if method == "ekf":
        return Affine(point=mean, value=centre, slope=difference / h[:, None, :], extra=None)
    # slope · (√D · factor) = difference  =>  slope = difference · factor⁻¹ / √D
    slope = torch.linalg.solve_triangular(factor, difference / math.sqrt(dim), upper=False, left=False)
    halfway = (plus + minus) / 2  # [B, D, P] the mean of each ± pair
    value = halfway.mean(dim=1)
    residual = halfway - value[:, None]
    off_centre = (centre - value)[..., None]
    extra = residual.mT @ residual / dim + UKF_BETA * off_centre @ off_centre.mT
    return Affine(point=mean, value=value, slope=slope, extra=symmetrise(extra))
