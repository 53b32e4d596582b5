"""The statistics of the held-out acceptance test: paired gains over recordings and the bar they must clear."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch


def log_ratio(before: torch.Tensor, after: torch.Tensor, floor: float) -> tuple[float, float, int]:
    """(mean, standard error, count) of log((before + floor) / (after + floor)) where it is finite; (−inf, inf, 0)
    if it is nowhere. `before`, `after`: [B] one error per recording, or [B, K] one per window of each recording —
    then the standard error is `hac_mean`'s, which weighs neighbouring windows of a record as dependent, and the
    count is the effective number of windows (what Student's t takes its degrees of freedom from), never more
    evidence than independent windows and never less than the records."""
    ratio = torch.log((before + floor) / (after + floor))
    if ratio.dim() == 2 and ratio.shape[1] > 1:
        return hac_mean(ratio)
    ratio = ratio.reshape(-1)
    ratio = ratio[torch.isfinite(ratio)]
    if ratio.numel() == 0:
        return -math.inf, math.inf, 0
    se = float(ratio.std() / math.sqrt(ratio.numel())) if ratio.numel() > 1 else math.inf
    return float(ratio.mean()), se, int(ratio.numel())


def hac_mean(d: torch.Tensor) -> tuple[float, float, int]:  # d: [B, K] per-window values, K windows in time order
    """(mean, standard error, effective count) of per-window values `d`, the windows of one record dependent.

    One long record gives a handful of held-out segments but many windows; windows next to each other share a
    state and an input, so they are not independent samples. Their dependence is taken as first-order
    autoregressive: ρ, the lag-one autocorrelation of the windows' deviations from the overall mean, pooled over
    records (so a difference between records counts as dependence too), clamped to [0, 0.99]; the effective
    count is n·(1 − ρ)/(1 + ρ) and the variance of the mean is inflated by the same factor. Where that leaves no
    more than one value per record, the test is the records' own: the mean and standard error of the records'
    means (Student's t over records, as without windows). A record with a non-finite window is left out whole."""
    ok = torch.isfinite(d).all(dim=1)
    d = d[ok].double()
    b, k = d.shape
    n = b * k
    if n == 0:
        return -math.inf, math.inf, 0
    mean = float(d.mean())
    if n < 2:
        return mean, math.inf, n
    e = d - mean
    gamma0 = float(e.pow(2).sum())
    if gamma0 <= 0:
        return mean, 0.0, n
    rho = min(max(float((e[:, 1:] * e[:, :-1]).sum()) / gamma0 * n / max(b * (k - 1), 1), 0.0), 0.99)
    inflation = (1 + rho) / (1 - rho)
    n_eff = n / inflation
    if n_eff <= b:  # the windows say no more than the records: the records' own test
        per = d.mean(dim=1)
        return float(per.mean()), float(per.std() / math.sqrt(b)) if b > 1 else math.inf, b
    return mean, math.sqrt(gamma0 / (n * (n - 1)) * inflation), int(n_eff)


def critical(margin: float, n: int) -> float:
    """How many standard errors a mean over `n` recordings must clear for the one-sided level that `margin`
    Gaussian standard errors give: Student's t with n − 1 degrees of freedom, as the standard error is estimated
    from the same few recordings (margin 2: 4.53 at n = 3, 2.65 at n = 6, 2.04 at n = 64; inf below n = 2)."""
    if n < 2:
        return math.inf
    from scipy.stats import norm, t

    return float(t.ppf(norm.cdf(margin), n - 1))


def level_text(margin: float, n: int, over: str = "") -> str:
    return f"margin {margin:g} as Student's t over {over or units_text(n)}"


def units_text(n: int, windows: int = 0, records: int = 0) -> str:
    """What a held-out test's count `n` counts: recordings, or (with `windows`) effective windows of records."""
    if not windows:
        return f"{n} held-out recording{'s' if n != 1 else ''}"
    return f"{n} effective of {windows} held-out windows in {records} recording{'s' if records != 1 else ''}"


@dataclass(frozen=True)
class Paired:
    """A paired comparison of held-out errors before and after adding a candidate, over recordings."""

    gain: float  # mean MSE reduction over the recordings where it is finite (−inf if none is)
    gain_se: float  # its standard error (inf below two recordings)
    log_ratio: float  # mean of log((before + floor) / (after + floor))
    log_ratio_se: float
    n: int  # recordings (or effective windows: `hac_mean`) the log ratio is taken over
    bar: float  # standard errors the log ratio must clear (`critical`)
    over: str = ""  # what `n` counts, in words (`units_text`)


def paired(before: torch.Tensor, after: torch.Tensor, floor: float, margin: float) -> Paired:
    """Paired gain and log error ratio of `after` against `before` ([B] held-out MSE per recording each, or
    [B, K] per window: `log_ratio`), with the bar for `margin` (`critical`); `floor` keeps the log ratio finite
    where an error is zero."""
    log_gain, log_se, n_rec = log_ratio(before, after, floor)
    bar = critical(margin, n_rec)
    windowed = before.dim() == 2 and before.shape[1] > 1
    over = units_text(n_rec, before.numel(), before.shape[0]) if windowed else units_text(n_rec)
    diff = (before - after).reshape(-1)
    finite = torch.isfinite(diff)
    gain = float(diff[finite].mean()) if finite.any() else -math.inf
    se = float(diff[finite].std() / math.sqrt(max(int(finite.sum()), 1))) if int(finite.sum()) > 1 else math.inf
    return Paired(gain, se, log_gain, log_se, n_rec, bar, over)
