"""Acceptance by held-out prediction, and the three verdicts.

The one-step screen (`find_effects`) proposes candidates; here each one is *tested*: added to the model with
its coefficients fitted by multiple shooting on held-in data (the model's own white-box parameters refit
alongside), and named only if it lowers the held-out multi-step error by more than the same fit achieves on
null data (the model's own simulation plus the data's noise level) plus `margin` paired standard errors.
Without a candidate the model is refit the same way (its own parameters only), so an effect never gets the
credit for a plain refit.

Verdicts (each with its numbers; distinct exit codes):

| verdict | when | exit |
|---|---|---|
| effects named | named effects remove ≥ `min_explained` of the held-out error above the null level | 0 |
| nothing missing | the refit model's held-out error is at the null level (or below `tolerance`) | 10 |
| unexplained structured residual | above the null level and no candidate (set) explains it | 11 |
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from typing import Any, cast

import torch

from mpsim import effects as fx
from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.library import Candidate, evaluate_effect, step_average
from mpsim.diagnose.params import KIND_COMPLEXITY, DiagnoseParams
from mpsim.diagnose.search import Diagnosis, Finding, model_sensitivities
from mpsim.diagnose.shooting import (
    horizon_from_data,
    null_data,
    own_parameters,
    shooting_fit,
    window_error,
    with_effect,
)
from mpsim.errors import ConfigError, DataError, did_you_mean
from mpsim.models.base import Model
from mpsim.models.capabilities import Interpretable

EFFECTS_NAMED, NOTHING_MISSING, UNEXPLAINED = "effects named", "nothing missing", "unexplained structured residual"
EXIT_CODES = {EFFECTS_NAMED: 0, NOTHING_MISSING: 10, UNEXPLAINED: 11}
#: how a candidate that could not be tested on these data begins its reason
NOT_TESTED = "not tested"
#: a simpler kind is preferred when its held-out error is within this factor of the best candidate's
SIMPLER_WITHIN = 1.25


def dynamic_rows(model: Model, data: Trajectories, targets: list[str] | None) -> list[int]:
    """State rows to search: `targets` if given, else every row except the kinematic ones (declared by the
    model — `model=equations` specs, white-box models whose equation for a state is another state — or by the
    data's metadata `kinematic: [...]`)."""
    names = list(data.state_names)
    if targets:
        for name in targets:
            if name not in names:
                raise ConfigError(
                    f"diagnose.targets names {name!r}, which is not a state.{did_you_mean(name, names)} "
                    f"States: {names}."
                )
        return [names.index(n) for n in targets]
    kinematic = set(getattr(model, "kinematic_states", None) or []) | set(data.meta.get("kinematic") or [])
    rows = [d for d, n in enumerate(names) if n not in kinematic]
    return rows or list(range(len(names)))


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
    null_gain: float  # the same fit's gain on null data
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

    def as_dict(self) -> dict[str, Any]:
        return {**self.__dict__, "test": self.test_text()}

    def test_text(self) -> str:
        """How far the log error ratio cleared the null fit's, in standard errors, against the bar ("" untested)."""
        if not (self.n_heldout and math.isfinite(self.log_ratio) and self.log_ratio_se > 0):
            return ""
        above = (self.log_ratio - max(self.null_log_ratio, 0.0)) / self.log_ratio_se
        return (
            f"log error ratio {self.log_ratio:.3g} ± {self.log_ratio_se:.2g} over {self.n_heldout} held-out "
            f"recordings: {above:.3g} standard errors above {max(self.null_log_ratio, 0.0):.3g} (bar {self.bar_se:.3g})"
        )


@dataclass
class Judgement:
    """The held-out verdict and everything it rests on."""

    verdict: str
    horizon: int
    error_given: float  # held-out multi-step MSE of the model as given
    error_refit: float  # ... after refitting its own parameters by multiple shooting
    error_null: float  # ... of the refit model on null data (its own simulation plus the noise level)
    error_final: float  # ... with the named effects
    explained: float  # share of (refit − null) removed by the named effects
    trials: list[Trial] = field(default_factory=list)
    model: Model | None = None  # the refit model with the named effects (never worse on held-out data)
    notes: list[str] = field(default_factory=list)

    @property
    def exit_code(self) -> int:
        return EXIT_CODES[self.verdict]

    @property
    def named(self) -> list[Trial]:
        return [t for t in self.trials if t.accepted] if self.verdict == EFFECTS_NAMED else []

    def as_dict(self) -> dict[str, Any]:
        out = {k: v for k, v in self.__dict__.items() if k not in ("model", "trials")}
        out["trials"] = [t.as_dict() for t in self.trials]
        out["named"] = [t.label for t in self.named]
        return out


def _fit_with(model: Model, effect, train: Trajectories, horizon: int, iters: int):
    """(model + effect with the effect's and the model's own parameters fitted by multiple shooting, fit)."""
    trial = with_effect(model, effect)
    free = [p for p in trial.effects[-1].parameters() if p.requires_grad] + own_parameters(trial)
    return trial, shooting_fit(trial, train, horizon, free, iters)


def judge(
    model: Model,
    diag: Diagnosis,
    library: list[Candidate],
    train: Trajectories,
    test: Trajectories,
    params: DiagnoseParams,
    seed: int = 0,
    test_candidates: bool = True,
) -> Judgement:
    """Test the screened candidates (strongest share of their row first) on held-out prediction; name the
    ones that pass, greedily, and return the verdict with the model that carries them. With
    `test_candidates=False` only the levels are measured (given, refit, null) and the verdict is *nothing
    missing* or *unexplained*: the caller tests the candidates another way (by finetuning a network)."""
    train = train.subset(slice(0, params.fit_trajectories))  # a handful of parameters: a few records suffice
    horizon = params.horizon or horizon_from_data(model, train, params.vpt_threshold)
    noise = torch.tensor(diag.noise_std, dtype=torch.float64)
    given = float(window_error(model, test, horizon).mean())
    base = copy.deepcopy(model)
    shooting_fit(base, train, min(horizon, params.fit_window), own_parameters(base), params.shooting_iters)
    e_base = window_error(base, test, horizon)
    if not float(e_base.mean()) <= given:  # the refit never makes the starting point worse
        base, e_base = copy.deepcopy(model), window_error(model, test, horizon)
    null_train = null_data(base, train, noise, seed + 11, segment=horizon)
    null_test = null_data(base, test, noise, seed + 12, segment=horizon)
    e_null = window_error(base, null_test, horizon)
    labels = {c.label(diag.state_names): c for c in library}
    floor = max(params.structured_factor * float(e_null.mean()), params.tolerance**2)
    if float(e_base.mean()) <= floor:  # at the null level: nothing to test
        return Judgement(
            NOTHING_MISSING,
            horizon,
            given,
            float(e_base.mean()),
            float(e_null.mean()),
            float(e_base.mean()),
            0.0,
            [],
            base,
            [],
        )
    if not test_candidates:
        note = "candidates are tested by finetuning the model with each one against the same finetune without it"
        return Judgement(
            UNEXPLAINED, horizon, given, float(e_base.mean()), float(e_null.mean()), float(e_base.mean()), 0.0,
            [], base, [note],
        )  # fmt: skip
    # the screen ranks (BIC-selected, screened ones first, then by share of their row); held-out data decide.
    # Each candidate is first tried alone on the refit model; the best passing one (the simplest kind among
    # those as good within their standard errors) is added, and the rest are tried again on top of it.
    ranked = [
        f for f in sorted(diag.findings, key=lambda f: (not f.accepted, -f.gain)) if f.label.split(": ", 1)[1] in labels
    ]
    # a delayed copy of a state imitates many terms within a step and needs the slow delay integrator: delayed
    # candidates are tried only when none of the others passes
    plain = [f for f in ranked if f.kind != "DelayedFeedback"][: params.max_candidates]
    delayed = [f for f in ranked if f.kind == "DelayedFeedback"][: params.max_candidates]
    current, e_current, trials = base, e_base, []
    pending = [(f, labels[f.label.split(": ", 1)[1]]) for f in plain]
    later = [(f, labels[f.label.split(": ", 1)[1]]) for f in delayed]
    if not pending:
        pending, later = later, []
    while pending:
        tried = [
            (
                f,
                c,
                *_trial(
                    current,
                    e_current,
                    base,
                    e_base,
                    e_null,
                    c,
                    f,
                    train,
                    test,
                    null_train,
                    null_test,
                    horizon,
                    params,
                    diag.state_names,
                ),
            )
            for f, c in pending
        ]
        passing = [t for t in tried if t[2].accepted]
        trials += [t[2] for t in tried if not t[2].accepted]
        if not passing and later and current is base:
            pending, later = later, []
            continue
        if not passing:
            break
        best_err = min(t[2].error_after for t in passing)
        close = [t for t in passing if t[2].error_after <= SIMPLER_WITHIN * best_err]
        chosen = min(close, key=lambda t: (KIND_COMPLEXITY.get(t[2].kind, 1), t[2].error_after))
        trials.append(chosen[2])
        current, e_current = chosen[3], chosen[4]
        if chosen[2].kind == "PeriodicForcing" and "phases" in chosen[2].effect:
            e_current = torch.full_like(e_base, chosen[2].error_after)  # measured after the warm-up window
            break  # its phases belong to the held-in recordings: nothing more is added on top of it
        # the others that passed alone are tried again on top of the chosen one
        pending = [(t[0], t[1]) for t in passing if t is not chosen]
    refit, final = float(e_base.mean()), float(e_current.mean())
    excess = max(refit - float(e_null.mean()), 1e-300)
    explained = (refit - final) / excess if any(t.accepted for t in trials) else 0.0
    notes = []
    if any(t.accepted for t in trials) and (final <= floor or explained >= params.min_explained):
        verdict = EFFECTS_NAMED
    elif refit <= floor:
        verdict = NOTHING_MISSING
        for t in trials:
            if t.accepted:  # below the null level nothing is named, however it scored
                t.accepted, t.reason = False, "the model is already at the null level: " + t.reason
        current = base
    else:
        verdict = UNEXPLAINED
        for t in trials:
            if t.accepted:
                t.accepted = False
                t.reason = (
                    f"helps on held-out data but leaves {1 - explained:.0%} of the error above the null level "
                    f"unexplained (needs ≥ {params.min_explained:.0%}): a partial fit, not a finding"
                )
        notes.append(_best_text(trials, refit, float(e_null.mean())))
        current = base
    return Judgement(
        verdict,
        horizon,
        given,
        refit,
        float(e_null.mean()),
        float(e_current.mean()) if verdict == EFFECTS_NAMED else refit,
        explained,
        trials,
        current,
        notes,
    )


def reported(effect, values: list[float], stderr: list[float]) -> tuple[dict[str, float], dict[str, tuple]]:
    """The parameters a report shows for a fitted effect, with 95 % intervals around exactly these values: the
    coefficient(s), or for a drive its amplitude, angular frequency and phase (delta method from a, b, log ω)."""
    if type(effect).__name__ == "PhasedDrive":  # amplitude, log ω, then one phase per recording
        amp, omega = values[0], math.exp(values[1])
        vals = {"amplitude": amp, "omega": omega}
        ses = {"amplitude": stderr[0], "omega": omega * stderr[1]}
    elif type(effect).__name__ == "PeriodicForcing" and len(values) >= 3:
        a, b, log_w = values[:3]
        sa, sb, sw = stderr[:3]
        amp, omega = math.hypot(a, b), math.exp(log_w)
        se_amp = math.hypot(a * sa, b * sb) / max(amp, 1e-300)
        se_phase = math.hypot(b * sa, a * sb) / max(amp**2, 1e-300)
        vals = {"amplitude": amp, "omega": omega, "phase": math.atan2(b, a)}
        ses = {"amplitude": se_amp, "omega": omega * sw, "phase": se_phase}
    else:
        keys = ["coef"] if len(values) == 1 else [f"coef[{i}]" for i in range(len(values))]
        vals = dict(zip(keys, values, strict=True))
        ses = dict(zip(keys, stderr, strict=True))
    return vals, {k: (v - 1.96 * ses[k], v + 1.96 * ses[k]) for k, v in vals.items()}


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


def _best_text(trials: list[Trial], refit: float, null: float) -> str:
    untested = [t for t in trials if t.reason.startswith(NOT_TESTED)]
    tested = [t for t in trials if not t.reason.startswith(NOT_TESTED)]
    skipped = f"{', '.join(t.label for t in untested)} {untested[0].reason}" if untested else ""
    if not tested:
        return skipped or "no candidate was left to test"
    best = min(tested, key=lambda t: t.error_after)
    left = (best.error_after - null) / max(refit - null, 1e-300)
    return (
        f"best candidate {best.label}: held-out MSE {refit:.3g} → {best.error_after:.3g} (null level {null:.3g}); "
        f"it would leave {max(left, 0):.0%} of the excess" + (f"; {skipped}" if skipped else "")
    )


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


def phase_warmup(horizon: int, n_times: int) -> int | None:
    """Steps at the start of each held-out record that fit a per-recording drive's phase (at most one horizon, a
    quarter of the record); None when no step would be left to test the drive on."""
    warm = max(2, min(horizon, (n_times - 1) // 4))
    return warm if n_times >= warm + 2 else None


def _too_short_for_phases(n_times: int, horizon: int) -> str:
    return (
        f"the held-out windows are {n_times - 1} steps (the model tracks the data for only {horizon} before its "
        "error passes diagnose.vpt_threshold), too short to fit a periodic drive's phase per recording and then "
        "test it; give diagnose.horizon=3 or more, or leave PeriodicForcing out of diagnose.kinds"
    )


def phased_heldout(current: Model, trial: Model, data: Trajectories, horizon: int, iters: int):
    """([B] MSE without, [B] MSE with a per-recording drive, the model with it) on `data` after a warm-up window.

    The drive's amplitude and frequency come from `trial` (fitted on held-in recordings); each recording's
    phase is estimated from its first quarter (at most one horizon): a least-squares fit of the one-step
    residual on sin ωt, cos ωt gives a start, multiple shooting over the warm-up window refines it. Both
    errors are measured on the rest of the record only."""
    from mpsim.diagnose.library import PhasedDrive
    from mpsim.diagnose.residual import one_step_residual

    drive = cast(Any, trial.effects[-1])  # the candidate drive (a Module list holds Modules)
    warm = phase_warmup(horizon, data.n_times)
    if warm is None:  # no step left to test on after the warm-up (`_trial` skips the candidate before this)
        raise DataError(f"diagnose: {_too_short_for_phases(data.n_times, horizon)}")
    head, tail = data.time_slice(0, warm + 1), data.time_slice(warm, data.n_times)
    res = one_step_residual(current, head)
    r = res.r[..., drive.target].mean(dim=2).nan_to_num()  # [B, warm]
    w = drive.omega
    x = torch.stack([torch.sin(w * res.t_mid), torch.cos(w * res.t_mid)], dim=1)  # [warm, 2]
    ab = torch.linalg.lstsq(x, r.T).solution  # [2, B]: A cos φ, A sin φ
    phases = torch.atan2(ab[1], ab[0]).tolist()
    amp = float(drive.coef.detach()[0])
    test_drive = PhasedDrive(amp, w, phases, target=drive.target, learnable=True)
    test_drive.bind(getattr(drive, "state_names", None) or [str(i) for i in range(data.state_dim)])
    model = with_effect(current, test_drive)
    shooting_fit(model, head, warm, [cast(PhasedDrive, model.effects[-1]).phases], iters)
    return window_error(current, tail, horizon), window_error(model, tail, horizon), model


def _trial(
    current,
    e_current,
    base,
    e_base,
    e_null,
    cand: Candidate,
    finding: Finding,
    train,
    test,
    null_train,
    null_test,
    horizon,
    params: DiagnoseParams,
    names,
) -> tuple[Trial, Model, torch.Tensor]:
    # the error the given model (own parameters refit) had above the null level: what effects may explain
    excess = max(float(e_base.mean()) - float(e_null.mean()), 0.0)
    phased = bool(cand.params.get("phased"))
    shortest = min(test.n_times, null_test.n_times)  # null records may be cut window by window
    if phased and phase_warmup(horizon, shortest) is None:  # not testable here: rejected, the others go on
        before = float(e_current.mean())
        return (
            Trial(
                label=finding.label, kind=finding.kind, screened=finding.accepted, effect={}, values={}, interval={},
                error_before=before, error_after=before, gain=0.0, gain_se=math.inf, null_gain=0.0, accepted=False,
                reason=f"{NOT_TESTED}: {_too_short_for_phases(shortest, horizon)}",
            ),
            current,
            e_current,
        )  # fmt: skip
    coef = list(finding.coef)[: 2 * len(train)] if phased else list(finding.coef)  # the fit's recordings only
    effect = cand.make_effect(coef, finding.target, names)
    fit_len = min(horizon, params.fit_window)
    trial, fit = _fit_with(current, effect, train, fit_len, params.shooting_iters)
    if phased:  # phases belong to recordings: held-out ones get theirs from a warm-up window
        e_current, e_after, _ = phased_heldout(current, trial, test, horizon, params.shooting_iters)
    else:
        e_after = window_error(trial, test, horizon)
    diff = e_current - e_after
    finite = torch.isfinite(diff)
    gain = float(diff[finite].mean()) if finite.any() else -math.inf
    se = float(diff[finite].std() / math.sqrt(max(int(finite.sum()), 1))) if int(finite.sum()) > 1 else math.inf
    # the test is on log error ratios per held-out recording: errors differ by orders of magnitude between
    # recordings, a multiplicative improvement does not
    floor = max(float(e_null.mean()), 1e-14)
    log_gain, log_se, n_rec = log_ratio(e_current, e_after, floor)
    bar = critical(params.margin, n_rec)
    if current is not base:  # null data of the model the candidate is added to (its integrator included)
        noise = (null_train.x - null_train.x).new_zeros(null_train.state_dim)  # clean: the comparison is paired
        null_train, null_test = null_data(current, null_train, noise, 21), null_data(current, null_test, noise, 22)
        e_null = window_error(current, null_test, horizon)
    # a phased drive carries one phase per fitted recording: the null records (window by window for short
    # horizons) get theirs from the same starting pairs, repeated
    null_coef = (coef * math.ceil(2 * len(null_train) / len(coef)))[: 2 * len(null_train)] if phased else coef
    null_trial, _ = _fit_with(
        current,
        cand.make_effect(null_coef, finding.target, names),
        null_train,
        fit_len,
        max(5, params.shooting_iters // 3),
    )
    if phased:
        before, after, _ = phased_heldout(current, null_trial, null_test, horizon, max(5, params.shooting_iters // 3))
        null_gain = float((before - after).mean())
        null_log = log_ratio(before, after, floor)[0]
    else:
        null_after = window_error(null_trial, null_test, horizon)
        null_gain = float((e_null - null_after).mean())
        null_log = log_ratio(e_null, null_after, floor)[0]
    fitted = trial.effects[-1]
    k = len(fit.values) - sum(p.numel() for p in own_parameters(trial))
    values, interval = reported(fitted, fit.values[:k], fit.stderr[:k])
    derived = ""
    if cand.kind == "CosineCoupling" and math.isfinite(values.get("coef", math.nan)):
        lag = phase_lag(trial, train, finding.target, values["coef"], (interval["coef"][1] - values["coef"]) / 1.96)
        if lag is not None:
            values, interval, derived = {**values, **lag[0]}, {**interval, **lag[1]}, lag[2]
        else:
            derived = "phase lag not separated: the model has no single sin-coupling parameter to pair with c"
    checks = [
        (fit.converged and math.isfinite(gain), "the multiple-shooting fit diverged"),
        (
            log_gain > max(null_log, 0.0) + bar * log_se,
            f"held-out error ratio e^{log_gain:.3g} (± {log_se:.2g} in log) is not above the null fit's "
            f"e^{max(null_log, 0):.3g} + {bar:.3g} standard errors ({level_text(params.margin, n_rec)})",
        ),
        (
            gain >= params.min_gain * excess,
            f"removes {gain / max(excess, 1e-300):.1%} of the held-out error the model had above the null level, below "
            f"{params.min_gain:.0%}: too small to be an effect (an integrator artefact or a detail of another term)",
        ),
    ]
    failed = [why for ok, why in checks if not ok]
    reason = (
        "; ".join(failed)
        if failed
        else (
            f"lowers the held-out MSE {float(e_current.mean()):.3g} → "
            f"{float(e_after.mean()):.3g}, above the null fit's gain"
        )
    )
    out = Trial(
        label=finding.label,
        kind=finding.kind,
        screened=finding.accepted,
        effect=fitted.config(),
        values=values,
        interval=interval,
        error_before=float(e_current.mean()),
        error_after=float(e_after.mean()),
        gain=gain,
        gain_se=se,
        null_gain=null_gain,
        accepted=not failed,
        reason=reason,
        derived=derived,
        log_ratio=log_gain,
        log_ratio_se=log_se,
        null_log_ratio=null_log,
        n_heldout=n_rec,
        bar_se=bar,
    )
    return out, trial, e_after
