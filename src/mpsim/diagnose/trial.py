"""One candidate's held-out trial: added to the model, fitted by multiple shooting on held-in records, and judged
by its paired gain on held-out records against the same fit on null data (`heldout.judge` runs the trials)."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any

import torch

from mpsim import effects as fx
from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.findings import Finding
from mpsim.diagnose.library import Candidate, evaluate_effect, step_average
from mpsim.diagnose.nuisance import model_sensitivities
from mpsim.diagnose.params import DiagnoseParams
from mpsim.diagnose.perrecord import (
    gain_heldout,
    gains_text,
    per_record,
    phase_warmup,
    phased_heldout,
    record_coef,
    too_short_for_phases,
)
from mpsim.diagnose.shooting import (
    NUMERICAL_FAILURES,
    ShootingFit,
    failure_text,
    heldout_errors,
    null_data,
    own_parameters,
    shooting_fit,
    with_effect,
)
from mpsim.diagnose.stats import Paired, level_text, log_ratio, paired, units_text
from mpsim.models.base import Model
from mpsim.models.capabilities import Interpretable

#: L-BFGS runs of a delayed feedback's multiple-shooting fit (each from where the last stopped, rescaled): one run
#: stops early in the valley of τ against the gain and the model's own parameters (τ 0.115 for a true 0.15)
DELAY_RESTARTS = 3
#: how a candidate that could not be tested on these data begins its reason
NOT_TESTED = "not tested"
#: how a candidate whose fit or held-out rollouts failed numerically begins its reason (its failure is its own: the
#: judgement goes on with the others)
FAILED = "failed"


@dataclass
class Trial:
    """One candidate tested on held-out data."""

    label: str
    kind: str
    screened: bool  # passed the one-step screen (only screened candidates can be named)
    effect: dict[str, Any]  # Hydra config with the multiple-shooting coefficients
    values: dict[str, float]  # the reported parameters (coef; or amplitude, omega, phase of a drive)
    interval: dict[str, tuple[float, float]]  # their 95 % intervals (cluster-robust Gauss–Newton, delta method)
    error_before: float  # held-out multi-step MSE (normalised) of the model it was added to
    error_after: float
    gain: float  # mean paired held-out MSE reduction
    gain_se: float
    null_gain: float  # the same fit's gain on null data (nan: not fitted there, it failed on the data already)
    accepted: bool
    reason: str
    derived: str = ""  # how derived values (a coupling's phase lag α and strength K) were obtained
    # the acceptance test: mean and standard error over held-out recordings of log(error before / after), the
    # same for the null fit (0 when judged by finetuning), the recordings, and the standard errors it had to clear
    log_ratio: float = math.nan
    log_ratio_se: float = math.nan
    null_log_ratio: float = math.nan
    n_heldout: int = 0
    bar_se: float = math.nan
    failure: str = ""  # the numerical failure that ended its trial ("" when it was judged): `FAILED` reasons
    heldout_over: str = ""  # what `n_heldout` counts, in words (recordings, or effective windows)

    def as_dict(self) -> dict[str, Any]:
        return {**self.__dict__, "test": self.test_text()}

    def test_text(self) -> str:
        """How far the log error ratio cleared the null fit's, in standard errors, against the bar ("" untested)."""
        if not (self.n_heldout and math.isfinite(self.log_ratio) and self.log_ratio_se > 0):
            return ""
        null = self.null_log_ratio if math.isfinite(self.null_log_ratio) else 0.0  # nan: not fitted to null data
        above = (self.log_ratio - max(null, 0.0)) / self.log_ratio_se
        return (
            f"log error ratio {self.log_ratio:.3g} ± {self.log_ratio_se:.2g} over "
            f"{self.heldout_over or units_text(self.n_heldout)}: {above:.3g} standard errors above "
            f"{max(null, 0.0):.3g} (bar {self.bar_se:.3g})"
        )


@dataclass(frozen=True)
class TrialSetting:
    """What the trials of one judgement share: the refit model's levels, the records and the settings."""

    base: Model  # the model as given with its own parameters refit by multiple shooting
    e_base: torch.Tensor  # [B] its held-out multi-step MSE per recording
    e_null: torch.Tensor  # [B'] ... on the null held-out records
    train: Trajectories  # held-in records the candidates are fitted on
    test: Trajectories  # held-out records
    null_train: Trajectories  # the base model's own simulation of `train`, plus the data's noise level
    null_test: Trajectories  # ... of `test`
    horizon: int  # steps of a held-out window
    params: DiagnoseParams
    names: list[str]  # state names
    window: int | None = None  # steps of a scored held-out window (`shooting.scored_window`; None: the horizon)


def try_candidate(
    s: TrialSetting, current: Model, e_current: torch.Tensor, cand: Candidate, finding: Finding
) -> tuple[Trial, Model, torch.Tensor]:
    """Add `cand` (the screen's `finding`) to `current` ([B] held-out MSE `e_current`), fit it by multiple shooting
    and judge it on held-out records: (the trial, the model with it, [B] its held-out MSE).

    A candidate whose computation fails numerically (a rollout the ODE solver gives up on, a float overflow, a
    linear-algebra routine on non-finite values: `NUMERICAL_FAILURES`) is rejected with that reason, and `current`
    is handed back unchanged: one candidate's failure never ends the judgement of the others."""
    stage = ["fitting it by multiple shooting on held-in records"]  # what it was doing, for a failure's reason
    try:
        return _try_candidate(s, current, e_current, cand, finding, stage)
    except NUMERICAL_FAILURES as exc:
        why = f"{FAILED} while {stage[0]}: {failure_text(exc)}"
        return _untested(finding, why, e_current, failure=why), current, e_current


def _try_candidate(
    s: TrialSetting, current: Model, e_current: torch.Tensor, cand: Candidate, finding: Finding, stage: list[str]
) -> tuple[Trial, Model, torch.Tensor]:
    """`try_candidate` itself; `stage[0]` says what it is doing."""
    # the error the given model (own parameters refit) had above the null level: what effects may explain
    excess = max(float(s.e_base.mean()) - float(s.e_null.mean()), 0.0)
    phased = bool(cand.params.get("phased"))
    own = per_record(cand)  # coefficients per recording: a drive's phase, an input's gain
    shortest = min(s.test.n_times, s.null_test.n_times)  # null records may be cut window by window
    if own and phase_warmup(s.horizon, shortest) is None:  # not testable here: rejected, the others go on
        return (
            _untested(finding, f"{NOT_TESTED}: {too_short_for_phases(shortest, s.horizon, cand)}", e_current),
            current,
            e_current,
        )
    coef = record_coef(cand, list(finding.coef), len(s.train))  # the fit's recordings only
    effect = cand.make_effect(coef, finding.target, s.names)
    trial, fit = fit_with(current, effect, s.train, min(s.horizon, s.params.fit_window), s.params.shooting_iters)
    stage[0] = "rolling the model with it out over held-out records"
    if phased:  # phases belong to recordings: held-out ones get theirs from a warm-up window
        e_current, e_after, _ = phased_heldout(current, trial, s.test, s.horizon, s.params.shooting_iters)
    elif own:  # so do gains
        e_current, e_after, _ = gain_heldout(current, trial, s.test, s.horizon, s.params.shooting_iters)
    else:
        e_after = heldout_errors(trial, s.test, s.horizon, s.window)
    # the test is on log error ratios per held-out recording: errors differ by orders of magnitude between
    # recordings, a multiplicative improvement does not
    floor = max(float(s.e_null.mean()), 1e-14)
    p = paired(e_current, e_after, floor, s.params.margin)
    stage[0] = "computing its reported values"
    values, interval, derived = _reported_values(cand, trial, fit, s.train, finding.target)
    # a fit that failed or ran off is the candidate's failure, with where it went; the checks below are then moot
    failure = _fit_failure(trial.effects[-1], fit, values) or diverged_heldout(e_current, e_after)
    # the null fit only raises the bar: a candidate that fails with it at zero is not fitted to null data too
    failed = failure or _failed_checks(p, 0.0, excess, s.params) + _beyond_record(trial.effects[-1], s.train)
    stage[0] = "fitting it to null data"
    null_gain, null_log = (math.nan, math.nan) if failed else _null_gain(s, current, cand, finding, coef, floor)
    if not failed:
        failed = _failed_checks(p, null_log, excess, s.params)
    reason = (
        "; ".join(failed)
        if failed
        else (
            f"lowers the held-out MSE {float(e_current.mean()):.3g} → "
            f"{float(e_after.mean()):.3g}, above the null fit's gain"
        )
    )
    out = Trial(
        label=fitted_label(finding.label, trial.effects[-1]),
        kind=finding.kind,
        screened=finding.accepted,
        effect=trial.effects[-1].config(),
        values=values,
        interval=interval,
        error_before=float(e_current.mean()),
        error_after=float(e_after.mean()),
        gain=p.gain,
        gain_se=p.gain_se,
        null_gain=null_gain,
        accepted=not failed,
        reason=reason,
        derived=derived,
        log_ratio=p.log_ratio,
        log_ratio_se=p.log_ratio_se,
        null_log_ratio=null_log,
        n_heldout=p.n,
        bar_se=p.bar,
        failure="; ".join(failure),
        heldout_over=p.over,
    )
    return out, trial, e_after


def fitted_label(label: str, effect) -> str:
    """The screen's label with a delayed feedback's fitted delay in place of its grid value (the screen tries
    a few multiples of the sampling step; the multiple-shooting fit moves τ continuously)."""
    if type(effect).__name__ in ("DeadZone", "InputSaturation"):
        return re.sub(rf"{effect.key}=[^,)]*", f"{effect.key}={effect.threshold:.4g}", label)
    if type(effect).__name__ != "DelayedFeedback":
        return label
    return re.sub(r"τ=[^,)]*", f"τ={effect.delay:.4g}", label)


def _beyond_record(effect, train: Trajectories) -> list[str]:
    """Why a fitted delay is no finding when it ran past the records (empty otherwise): there its history is the
    first state held, a constant per recording, not a delayed state."""
    span = float(train.t[-1] - train.t[0])
    if type(effect).__name__ != "DelayedFeedback" or effect.delay < span:
        return []
    return [f"the fitted delay {effect.delay:.4g} is longer than the records ({span:.4g}): not a delay they can show"]


def _untested(finding: Finding, reason: str, e_current: torch.Tensor, failure: str = "") -> Trial:
    """The trial of a candidate that cannot be tested on these records, or whose test failed (`failure`): rejected
    with `reason`, errors unchanged."""
    before = float(e_current.mean())
    return Trial(
        label=finding.label, kind=finding.kind, screened=finding.accepted, effect=finding.effect if failure else {},
        values={}, interval={}, error_before=before, error_after=before, gain=0.0, gain_se=math.inf, null_gain=0.0,
        accepted=False, reason=reason, failure=failure,
    )  # fmt: skip


def _fit_failure(effect, fit: ShootingFit, values: dict[str, float]) -> list[str]:
    """Why the multiple-shooting fit of `effect` is the candidate's failure (empty: it is not): it did not converge
    (where it stopped and why), or a reported value ran off to infinity or nan (`values`: `reported`'s)."""
    if not fit.converged:
        why = fit.failure or "a non-finite loss"
        if not fit.stopped_at:
            return [f"{FAILED}: the multiple-shooting fit diverged ({why})"]
        k = len(values_of(effect))  # the effect's come first, then the model's own parameters
        at, _ = reported(effect, fit.stopped_at[:k], [math.nan] * k)
        ran = ", ".join(f"{key} {v:.3g}" for key, v in at.items())
        if fit.stopped_at == fit.values:  # failed where it started (the screen's coefficients)
            return [f"{FAILED}: the multiple-shooting fit could not start from the screen's {ran}: {why}"]
        return [f"{FAILED}: the multiple-shooting fit ran to {ran}, where {why}"]
    return ran_off(values)


def ran_off(values: dict[str, float]) -> list[str]:
    """Why reported values that ran off to infinity or nan are the candidate's failure (empty: none did)."""
    off = {key: v for key, v in values.items() if not math.isfinite(v)}
    if not off:
        return []
    return [f"{FAILED}: the fit ran off ({', '.join(f'{key} {v}' for key, v in off.items())})"]


def values_of(effect) -> list[float]:
    """The effect's free parameters' values, flattened in the order a fit lists them."""
    free = [p for p in effect.parameters() if p.requires_grad]
    return torch.cat([p.detach().reshape(-1).double().cpu() for p in free]).tolist() if free else []


def diverged_heldout(e_current: torch.Tensor, e_after: torch.Tensor) -> list[str]:
    """Why held-out rollouts that diverge with the candidate and not without it are its failure (empty: none do).
    ([B] held-out MSE per recording without and with it.)"""
    lost = torch.isfinite(e_current) & ~torch.isfinite(e_after)
    if lost.dim() == 2:  # per window: a record is lost when any of its windows is
        lost = lost.any(dim=1)
    if not bool(lost.any()):
        return []
    return [
        f"{FAILED}: with it the held-out rollouts of {int(lost.sum())} of {len(lost)} recordings diverge "
        "(they do not without it)"
    ]


def _null_gain(
    s: TrialSetting, current: Model, cand: Candidate, finding: Finding, coef: list[float], floor: float
) -> tuple[float, float]:
    """(mean held-out MSE gain, mean log error ratio) of the same fit on null records, where nothing is missing."""
    phased, own = bool(cand.params.get("phased")), per_record(cand)
    null_train, null_test, e_null = s.null_train, s.null_test, s.e_null
    if current is not s.base:  # null data of the model the candidate is added to (its integrator included)
        noise = (null_train.x - null_train.x).new_zeros(null_train.state_dim)  # clean: the comparison is paired
        null_train, null_test = null_data(current, null_train, noise, 21), null_data(current, null_test, noise, 22)
        e_null = heldout_errors(current, null_test, s.horizon, s.window)
    # a phased drive carries one phase per fitted recording: the null records (window by window for short
    # horizons) get theirs from the same starting pairs, repeated
    null_coef = record_coef(cand, coef, len(null_train)) if own else coef
    iters = max(5, s.params.shooting_iters // 3)
    null_effect = cand.make_effect(null_coef, finding.target, s.names)
    null_trial, _ = fit_with(current, null_effect, null_train, min(s.horizon, s.params.fit_window), iters, False)
    if own:
        heldout = phased_heldout if phased else gain_heldout
        before, after, _ = heldout(current, null_trial, null_test, s.horizon, iters)
        return float((before - after).mean()), log_ratio(before, after, floor)[0]
    null_after = heldout_errors(null_trial, null_test, s.horizon, s.window)
    return float((e_null - null_after).mean()), log_ratio(e_null, null_after, floor)[0]


def _reported_values(
    cand: Candidate, trial: Model, fit: ShootingFit, train: Trajectories, target: int
) -> tuple[dict[str, float], dict[str, tuple], str]:
    """(the fitted effect's reported values, their 95 % intervals, how derived values were obtained)."""
    k = len(fit.values) - sum(p.numel() for p in own_parameters(trial))
    values, interval = reported(trial.effects[-1], fit.values[:k], fit.stderr[:k])
    derived = ""
    # a phase lag pairs the first harmonics (a higher harmonic's cos term is another harmonic's lag: c alone)
    if cand.kind == "CosineCoupling" and cand.harmonic == 1 and math.isfinite(values.get("coef", math.nan)):
        lag = phase_lag(trial, train, target, values["coef"], (interval["coef"][1] - values["coef"]) / 1.96)
        if lag is not None:
            values, interval, derived = {**values, **lag[0]}, {**interval, **lag[1]}, lag[2]
        else:
            derived = "phase lag not separated: the model has no single sin-coupling parameter to pair with c"
    if cand.kind == "InputGain":
        derived = gains_text(fit.values[:k], fit.stderr[:k])
    return values, interval, derived


def _failed_checks(p: Paired, null_log: float, excess: float, params: DiagnoseParams) -> list[str]:
    """Why a candidate whose fit converged is not named (empty: it passed)."""
    checks = [
        (math.isfinite(p.gain), "its held-out rollouts diverged"),
        (
            p.log_ratio > max(null_log, 0.0) + p.bar * p.log_ratio_se,
            f"held-out error ratio e^{p.log_ratio:.3g} (± {p.log_ratio_se:.2g} in log) is not above the null fit's "
            f"e^{max(null_log, 0):.3g} + {p.bar:.3g} standard errors ({level_text(params.margin, p.n, p.over)})",
        ),
        (
            p.gain >= params.min_gain * excess,
            f"removes {p.gain / max(excess, 1e-300):.1%} of the held-out error the model had above the null level, "
            f"below {params.min_gain:.0%}: too small to be an effect (an integrator artefact or a detail of another "
            "term)",
        ),
    ]
    return [why for ok, why in checks if not ok]


def fit_with(model: Model, effect, train: Trajectories, horizon: int, iters: int, stderr: bool = True):
    """(model + effect with the effect's and the model's own parameters fitted by multiple shooting, fit; its
    standard errors only with `stderr`)."""
    trial = with_effect(model, effect)
    free = [p for p in trial.effects[-1].parameters() if p.requires_grad] + own_parameters(trial)
    # a delay's τ trades against its gain and the model's own parameters along a curved valley: L-BFGS restarts
    restarts = DELAY_RESTARTS if type(effect).__name__ == "DelayedFeedback" else 1
    return trial, shooting_fit(trial, train, horizon, free, iters, stderr, restarts)


def reported(effect, values: list[float], stderr: list[float]) -> tuple[dict[str, float], dict[str, tuple]]:
    """The parameters a report shows for a fitted effect, with 95 % intervals around exactly these values: the
    coefficient(s) (a parameter drift's rate `s`), for a delayed feedback c and its delay τ (fitted as log τ), or
    for a drive its amplitude, angular frequency and phase (delta method from a, b, log ω)."""
    if type(effect).__name__ in ("DeadZone", "InputSaturation"):  # the log threshold
        key = effect.key
        vals, ses = {key: _exp(values[0])}, {key: _exp(values[0]) * stderr[0]}
    elif type(effect).__name__ == "InputGain":  # g_b − 1 per recording: the gains' mean and range
        g = [1.0 + v for v in values]
        lo, hi = min(range(len(g)), key=g.__getitem__), max(range(len(g)), key=g.__getitem__)
        vals = {"gain mean": sum(g) / len(g), "gain min": g[lo], "gain max": g[hi]}
        ses = {
            "gain mean": math.sqrt(sum(e * e for e in stderr)) / len(g),
            "gain min": stderr[lo],
            "gain max": stderr[hi],
        }
    elif type(effect).__name__ == "PhasedDrive":  # amplitude, log ω, then one phase per recording
        amp, omega = values[0], _exp(values[1])
        vals = {"amplitude": amp, "omega": omega}
        ses = {"amplitude": stderr[0], "omega": omega * stderr[1]}
    elif type(effect).__name__ == "DelayedFeedback" and len(values) == 2:  # c, then log τ
        tau = _exp(values[1])
        vals = {"coef": values[0], "delay": tau}
        ses = {"coef": stderr[0], "delay": tau * stderr[1]}
    elif type(effect).__name__ == "PeriodicForcing" and len(values) >= 3:
        a, b, log_w = values[:3]
        sa, sb, sw = stderr[:3]
        amp, omega = math.hypot(a, b), _exp(log_w)
        se_amp = math.hypot(a * sa, b * sb) / max(amp, 1e-300)
        se_phase = math.hypot(b * sa, a * sb) / max(amp**2, 1e-300)
        vals = {"amplitude": amp, "omega": omega, "phase": math.atan2(b, a)}
        ses = {"amplitude": se_amp, "omega": omega * sw, "phase": se_phase}
    else:  # a parameter drift's one coefficient is its relative rate s of p·(1 + s·t)
        one = "s" if type(effect).__name__ == "ParameterDrift" else "coef"
        nodes = getattr(effect, "nodes", None)  # a per-node effect: one coefficient per listed node
        keys = (
            [one]
            if len(values) == 1
            else [f"coef[node {n}]" for n in nodes]
            if nodes is not None
            else [f"coef[{i}]" for i in range(len(values))]
        )
        vals = dict(zip(keys, values, strict=True))
        ses = dict(zip(keys, stderr, strict=True))
    return vals, {k: (v - 1.96 * ses[k], v + 1.96 * ses[k]) for k, v in vals.items()}


def _exp(log_value: float) -> float:
    """e^x of a parameter fitted as its log (a delay, a frequency): inf where a fit ran it past the floats (the
    candidate then fails as run off, `_fit_failure`), not an OverflowError."""
    try:
        return math.exp(log_value)
    except OverflowError:  # past e^709.78
        return math.inf


def phase_lag(
    model: Model, data: Trajectories, row: int, c: float, c_se: float
) -> tuple[dict[str, float], dict[str, tuple], str] | None:
    """α and K of K·Σ_j sin(θ_j − θ_i − α) = K cos α·Σ sin(θ_j − θ_i) − K sin α·Σ cos(θ_j − θ_i), from a named
    cos-coupling coefficient c (= −K sin α) and the model's own sin coupling (= K cos α, refit beside c).

    The model's sin coupling is found among its own parameters as the one whose sensitivity on `row` is
    proportional to Σ_j sin(θ_j − θ_i) (cosine similarity ≥ 0.999); None when no parameter is (a black-box
    model, or a coupling written another way): the report then gives c alone. The intervals carry c's
    uncertainty only (the sin coupling held at its fitted value), which the returned note says.
    """
    values_now = getattr(model, "parameters_now", None)
    sens = model_sensitivities(model, data)  # [B, T-1, N, D, P] or None
    if sens is None or values_now is None or not isinstance(model, Interpretable):
        return None
    sine = fx.SineCoupling(1.0, target=row, source=row).bind(data.state_names)
    feat = step_average(evaluate_effect(sine, data))[..., 0].flatten()  # [B·(T−1)·N]
    current = values_now()
    for j, label in enumerate(model.sensitivity_names()):
        col = sens[..., row, j].flatten()
        ok = torch.isfinite(col) & torch.isfinite(feat)
        f, g = feat[ok], col[ok]
        norm = float(f.norm() * g.norm())
        if label not in current or current[label].numel() != 1 or norm == 0.0:
            continue  # per-node entries cannot be one coupling constant
        if float(f @ g) / norm < 0.999:
            continue
        k_cos = float(current[label].detach()) * float(f @ g) / float(f @ f)  # K cos α, in the library's Σ sin units
        k = math.hypot(k_cos, c)
        alpha = math.atan2(-c, k_cos)
        se_alpha = abs(k_cos) * c_se / max(k * k, 1e-300)
        se_k = abs(c) * c_se / max(k, 1e-300)
        vals = {"alpha": alpha, "K": k}
        interval = {
            "alpha": (alpha - 1.96 * se_alpha, alpha + 1.96 * se_alpha),
            "K": (k - 1.96 * se_k, k + 1.96 * se_k),
        }
        note = (
            f"phase lag from the cos coefficient c = {c:.4g} and the model's own sin coupling `{label}` refit to "
            f"K cos α = {k_cos:.4g}: α = atan2(−c, K cos α), K = hypot; intervals from c's uncertainty only"
        )
        return vals, interval, note
    return None
