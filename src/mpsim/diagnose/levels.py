"""Where noise sets the bar of the held-out judgement: which rows' one-step residual is noise (`noise_dominated`:
every kind is then tried held out), and when a null level cannot back a claim of completeness (`inflated_null`:
latent starts estimated per window carry the estimator's error into it)."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from mpsim.diagnose.findings import Diagnosis
    from mpsim.diagnose.trial import TrialSetting


#: a row's one-step residual is noise-dominated when its RMS is at most this many times the null data's (the
#: model's own simulation with the data's noise, differenced the same way): what the residual shows there is noise
NOISE_DOMINATED = 1.5


def noise_dominated(diag: Diagnosis) -> set[int]:
    """The searched rows whose one-step residual is noise-dominated (`NOISE_DOMINATED`)."""
    names = list(diag.state_names)
    rows = [names.index(n) for n in diag.searched] if diag.searched else range(len(names))
    return {
        d
        for d in rows
        if d < len(diag.residual_rms)
        and d < len(diag.null_rms)
        and diag.residual_rms[d] <= NOISE_DOMINATED * diag.null_rms[d]
    }


#: *nothing missing* with unmeasured states needs the held-out MSE within this factor of what the measured channels'
#: noise allows (their noise variance, normalised), unless the null level itself is that low
NOISE_FLOOR_FACTOR = 4.0


def inflated_null(s: TrialSetting, noise_std: list[float]) -> str:
    """Why the null level cannot back a claim of completeness ("" when it can). With unmeasured states every window's
    latent start is estimated from its own samples, on the null data as on the data: the null level then holds the
    estimator's error too, and a missing effect smaller than that error hides under it (an oscillator at 8.5
    samples a period: a missing cubic that changes the output 30× the noise, held-out MSE 8.4e-4 against a null
    level of 4.3e-4). *Nothing missing* then needs the refit model's held-out MSE within `NOISE_FLOOR_FACTOR` of the
    measured channels' noise variance (normalised; the data's estimate) or below `tolerance`; fully measured data
    keep the null level (there it is the noise, or a chaotic system's own divergence)."""
    observed = s.test.observed_index
    if len(observed) == s.test.state_dim or not noise_std:
        return ""
    std = s.base.state_std.detach().double().cpu().reshape(-1)
    parts = [(noise_std[d] / float(std[d])) ** 2 for d in observed if d < len(noise_std) and d < len(std)]
    if not parts:
        return ""
    noise = sum(parts) / len(parts)
    e_base, e_null = float(s.e_base.mean()), float(s.e_null.mean())
    bar = max(NOISE_FLOOR_FACTOR * noise, s.params.tolerance**2)
    if e_null <= bar or e_base <= bar:
        return ""
    return (
        f"not *nothing missing*: the refit model's held-out MSE {e_base:.3g} is near the null level {e_null:.3g}, but "
        f"that level is {e_null / max(noise, 1e-300):.3g}× the measured channels' noise ({noise:.3g}, normalised): "
        "each window's unmeasured start is estimated from its own samples, and that estimate's error sets the null "
        "level here, so an effect smaller than it cannot be seen. Nothing is claimed; longer windows "
        "(diagnose.horizon) or a better-sampled record would tell"
    )
