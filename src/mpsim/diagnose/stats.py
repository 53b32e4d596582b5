"""The statistics of the held-out acceptance test: paired gains over recordings and the bar they must clear."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch


def log_ratio(before: torch.Tensor, after: torch.Tensor, floor: float) -> tuple[float, float, int]:
    """(mean, standard error, count) over the recordings where log((before + floor) / (after + floor)) is
    finite; (−inf, inf, 0) if none is."""
    ratio = torch.log((before + floor) / (after + floor))
    ratio = ratio[torch.isfinite(ratio)]
    if ratio.numel() == 0:
        return -math.inf, math.inf, 0
    se = float(ratio.std() / math.sqrt(ratio.numel())) if ratio.numel() > 1 else math.inf
    return float(ratio.mean()), se, int(ratio.numel())


def critical(margin: float, n: int) -> float:
    """How many standard errors a mean over `n` recordings must clear for the one-sided level that `margin`
    Gaussian standard errors give: Student's t with n − 1 degrees of freedom, as the standard error is estimated
    from the same few recordings (margin 2: 4.53 at n = 3, 2.65 at n = 6, 2.04 at n = 64; inf below n = 2)."""
    if n < 2:
        return math.inf
    from scipy.stats import norm, t

    return float(t.ppf(norm.cdf(margin), n - 1))


def level_text(margin: float, n: int) -> str:
    return f"margin {margin:g} as Student's t over {n} held-out recording{'s' if n != 1 else ''}"


@dataclass(frozen=True)
class Paired:
    """A paired comparison of held-out errors before and after adding a candidate, over recordings."""

    gain: float  # mean MSE reduction over the recordings where it is finite (−inf if none is)
    gain_se: float  # its standard error (inf below two recordings)
    log_ratio: float  # mean of log((before + floor) / (after + floor))
    log_ratio_se: float
    n: int  # recordings the log ratio is taken over
    bar: float  # standard errors the log ratio must clear (`critical`)


def paired(before: torch.Tensor, after: torch.Tensor, floor: float, margin: float) -> Paired:
    """Paired gain and log error ratio of `after` against `before` ([B] held-out MSE per recording each), with
    the bar for `margin` (`critical`); `floor` keeps the log ratio finite where an error is zero."""
    log_gain, log_se, n_rec = log_ratio(before, after, floor)
    bar = critical(margin, n_rec)
    diff = before - after
    finite = torch.isfinite(diff)
    gain = float(diff[finite].mean()) if finite.any() else -math.inf
    se = float(diff[finite].std() / math.sqrt(max(int(finite.sum()), 1))) if int(finite.sum()) > 1 else math.inf
    return Paired(gain, se, log_gain, log_se, n_rec, bar)
