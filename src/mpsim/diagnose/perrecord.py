"""Candidates with coefficients of their own in every recording — a drive's phase (`PhasedDrive`), an input's gain
(`InputGain`): they belong to the records, not to the model, so held-out records get theirs from a warm-up window
(their first quarter, at most one horizon) and are scored on the rest."""

from __future__ import annotations

import copy
import math
from typing import Any, cast

import torch

from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.library import Candidate, PhasedDrive
from mpsim.diagnose.residual import one_step_residual
from mpsim.diagnose.shooting import shooting_fit, window_error, with_effect
from mpsim.effects.inputs import InputGain
from mpsim.errors import DataError
from mpsim.models.base import Model


def gains_text(rel: list[float], stderr: list[float]) -> str:
    """How a per-recording gain's fitted gains (g_b − 1 in `rel`) spread, and whether they agree: gains that agree
    within their errors are one gain of the input for every record — where the spec fits the input's coefficient
    (a 1/J, 1/m), indistinguishable from it on these data, not a per-recording finding."""
    g = torch.tensor(rel, dtype=torch.float64) + 1.0
    se = torch.tensor(stderr, dtype=torch.float64)
    sd = float(g.std()) if g.numel() > 1 else 0.0
    typical = float(se[torch.isfinite(se)].median()) if bool(torch.isfinite(se).any()) else math.inf
    text = f"gains of {g.numel()} held-in records: mean {float(g.mean()):.4g}, spread (sd) {sd:.3g}"
    if sd <= 2 * typical:
        text += (
            f" — within twice their standard error ({typical:.3g}): one gain for every record; where the spec fits "
            "the input's coefficient, indistinguishable from it on these data"
        )
    return text


def phase_warmup(horizon: int, n_times: int) -> int | None:
    """Steps at the start of each held-out record that fit a per-recording drive's phase (at most one horizon, a
    quarter of the record); None when no step would be left to test the drive on."""
    warm = max(2, min(horizon, (n_times - 1) // 4))
    return warm if n_times >= warm + 2 else None


def per_record(cand: Candidate) -> bool:
    """Whether the candidate has coefficients of its own in every recording (a drive's phase, an input's gain):
    held-out records get theirs from a warm-up window."""
    return bool(cand.params.get("phased")) or getattr(cand, "kind", "") == "InputGain"


def record_coef(cand: Candidate, coef: list[float], n_records: int) -> list[float]:
    """A per-recording candidate's coefficients for `n_records` recordings from those of others (the screen's,
    the held-in fit's): the first ones, repeated where there are more recordings (a drive's (a, b) pair each, a
    gain's c each); any other candidate's as they are."""
    if not per_record(cand):
        return list(coef)
    if getattr(cand, "kind", "") == "InputGain":  # every gain starts at 1: the part all recordings share is the
        return [0.0] * n_records  # model's own input coefficient, which the screen projected out (not identified)
    width = 2 if cand.params.get("phased") else 1
    return (list(coef) * math.ceil(width * n_records / max(len(coef), 1)))[: width * n_records]


def too_short_for_phases(n_times: int, horizon: int, cand: Candidate | None = None) -> str:
    what, kind = (
        ("an input's gain", "InputGain")
        if getattr(cand, "kind", "") == "InputGain"
        else ("a periodic drive's phase", "PeriodicForcing")
    )
    return (
        f"the held-out windows are {n_times - 1} steps (the model tracks the data for only {horizon} before its "
        f"error passes diagnose.vpt_threshold), too short to fit {what} per recording and then test it; give "
        f"diagnose.horizon=3 or more, or leave {kind} out of diagnose.kinds"
    )


def gain_heldout(current: Model, trial: Model, data: Trajectories, horizon: int, iters: int):
    """([B] MSE without, [B] MSE with a per-recording input gain, the model with it) on `data` after a warm-up
    window: each held-out recording's gain is fitted by multiple shooting over its first quarter (at most one
    horizon), started from the held-in recordings' mean gain, the model's own parameters as `trial` has them;
    both errors are measured on the rest of the record only."""
    gain = cast(Any, trial.effects[-1])  # the candidate gain (a Module list holds Modules)
    warm = phase_warmup(horizon, data.n_times)
    if warm is None:  # no step left to test on after the warm-up (`try_candidate` skips the candidate before this)
        raise DataError(f"diagnose: {too_short_for_phases(data.n_times, horizon)}")
    head, tail = data.time_slice(0, warm + 1), data.time_slice(warm, data.n_times)
    mean = sum(gain.gains) / len(gain.gains)
    test_gain = InputGain(gain.input_ref, [mean] * len(data), target=gain.target, learnable=True)
    test_gain.bind(getattr(gain, "state_names", None) or [str(i) for i in range(data.state_dim)])
    model = copy.deepcopy(trial)
    model.effects[-1] = test_gain.to(dtype=trial.state_mean.dtype, device=trial.state_mean.device)
    shooting_fit(model, head, warm, [cast(InputGain, model.effects[-1]).coef], iters, stderr=False)
    return window_error(current, tail, horizon), window_error(model, tail, horizon), model


def phased_heldout(current: Model, trial: Model, data: Trajectories, horizon: int, iters: int):
    """([B] MSE without, [B] MSE with a per-recording drive, the model with it) on `data` after a warm-up window.

    The drive's amplitude and frequency come from `trial` (fitted on held-in recordings); each recording's
    phase is estimated from its first quarter (at most one horizon): a least-squares fit of the one-step
    residual on sin ωt, cos ωt gives a start, multiple shooting over the warm-up window refines it. Both
    errors are measured on the rest of the record only."""
    drive = cast(Any, trial.effects[-1])  # the candidate drive (a Module list holds Modules)
    warm = phase_warmup(horizon, data.n_times)
    if warm is None:  # no step left to test on after the warm-up (`try_candidate` skips the candidate before this)
        raise DataError(f"diagnose: {too_short_for_phases(data.n_times, horizon)}")
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
    shooting_fit(model, head, warm, [cast(PhasedDrive, model.effects[-1]).phases], iters, stderr=False)
    return window_error(current, tail, horizon), window_error(model, tail, horizon), model
