"""The residual loop's settings: one object (the `diagnose:` config group's schema and the library's argument)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from mpsim.errors import ConfigError, did_you_mean

#: effect kinds of the default candidate library (class names in `mpsim.effects`), each with its complexity: among
#: candidates that predict held-out data equally well the simplest kind is named (a delayed copy of a state imitates
#: damping within a step; a drive needs three numbers). The one list of kinds: the library, the config's default
#: and the held-out judgement read it from here.
KIND_COMPLEXITY = {
    "Bias": 0,
    "LinearDamping": 0,
    "QuadraticDrag": 1,
    "CubicStiffness": 1,
    "DryFriction": 1,
    "DiffusiveCoupling": 1,
    "SineCoupling": 1,
    "CosineCoupling": 1,
    "PeriodicForcing": 2,
    "ParameterDrift": 2,
    "InputGain": 2,
    "DeadZone": 1,
    "InputSaturation": 1,
    "DelayedFeedback": 3,
}
DEFAULT_KINDS = list(KIND_COMPLEXITY)
#: harmonics k of the phase couplings in the library: sin/cos(k(θ_j − θ_i)) for each k, per source state. Each
#: harmonic counts as a kind of its own where the loop keeps one candidate per kind (the screen's best of each kind,
#: the held-out stage's one trial per kind and row), so a second harmonic is never crowded out by the first.
HARMONICS = (1, 2, 3)
#: harmonics are the simpler the lower: k adds HARMONIC_STEP × (k − 1) to its kind's complexity (k = 3 stays below
#: a drive's 2, and every first-harmonic kind of complexity 1 is simpler than any higher harmonic)
HARMONIC_STEP = 0.25


def complexity(kind: str, harmonic: int = 1) -> float:
    """A candidate's complexity: its kind's (`KIND_COMPLEXITY`, 1 if not listed), plus its harmonic's above k = 1."""
    return KIND_COMPLEXITY.get(kind, 1) + HARMONIC_STEP * (harmonic - 1)


@dataclass
class DiagnoseParams:
    """Settings of `mpsim diagnose` (every field is a `diagnose.<name>=` override).

    Screen (one-step residual regression, fast):
        kinds: effect kinds in the candidate library.
        delays: delays of DelayedFeedback candidates (null: 1, 2, 4, 8 sampling steps).
        targets: state rows searched (null: the dynamic rows — every row except the kinematic ones the model,
            e.g. a `model=equations` spec, or the data's metadata declare: θ̇ = ω carries no physics).
        n_boot, min_gain, null_factor, min_inclusion: a screened candidate must be selected by BIC, explain
            ≥ min_gain of its row's residual and ≥ null_factor × what any candidate explains on null data, and
            be selected in ≥ min_inclusion of bootstrap resamples over trajectories.
        screen_trajectories: held-in trajectories the screen uses (the first this many): a few coefficients need
            few, and the bootstrap's cost grows with them — as their cube for a drive with a phase per recording,
            whose two columns per recording enter every fit (200 recordings: minutes; 64: seconds).
    Acceptance (held-out prediction):
        max_candidates: a network's screened candidates finetuned with it (fix=true), strongest share of their row
            first. The held-out trials of a model judged with its network (or equations) frozen are not capped by
            it: they take the best candidate of each effect kind on each searched row — the screen's BIC-selected
            one, else the one of that kind that explains most of the row alone if that is ≥ min_gain — at most one
            per kind and row (each harmonic of a phase coupling a kind; delayed feedback only when no other kind
            passes), so the one-step fit never decides which kind the held-out test sees.
        margin: a candidate is named only if its held-out multi-step error gain exceeds the gain the same fit
            achieves on null data plus `margin` standard errors (paired over held-out trajectories; Student's t at
            the level `margin` has for a Gaussian, as the standard error comes from those few trajectories), and
            removes at least `min_gain` of the held-out error the model had above the null level.
        min_explained: the named effects must remove this share of the held-out error above the null level;
            otherwise the verdict is *unexplained structured residual* (a partial fit is not a finding).
        structured_factor, tolerance: the residual is at the null level ("nothing missing") when the held-out
            multi-step MSE is ≤ structured_factor × its value on null data, or its RMSE ≤ tolerance (normalised).
        shooting_iters: L-BFGS iterations of each multiple-shooting fit.
        fit_trajectories: held-in trajectories the multiple-shooting fits use (the first this many; more cost
            time roughly in proportion, and a handful of parameters needs few).
        horizon: steps of the held-out evaluation windows (null: from the data — the model's own valid
            prediction time on held-in data, the whole record when it never loses track).
        fit_window: the multiple-shooting fits use windows of at most this many steps (short windows keep the
            fit of oscillators well-conditioned; the held-out evaluation still uses `horizon`).
        vpt_threshold: valid prediction time: until the normalised rollout error exceeds this.
    Fix (fix=true):
        fix_lr_factor: the finetune runs at trainer.lr × this (it starts near the optimum).
        rounds: effects added one per round (the strongest), each followed by a finetune and a new diagnosis.
        jobs: a network's finetunes (the control and each candidate) run in this many processes at once, one
            thread each (null: one per CPU core on a CPU, one at a time on a GPU). Results do not depend on it
            beyond floating-point summation order.
    """

    kinds: list[str] = field(default_factory=lambda: list(DEFAULT_KINDS))
    delays: list[float] | None = None
    targets: list[str] | None = None
    n_boot: int = 100
    screen_trajectories: int = 64
    min_gain: float = 0.05
    null_factor: float = 3.0
    min_inclusion: float = 0.8
    max_candidates: int = 3
    margin: float = 2.0
    min_explained: float = 0.8
    structured_factor: float = 2.0
    tolerance: float = 1.0e-3
    shooting_iters: int = 25
    fit_trajectories: int = 16
    horizon: int | None = None
    fit_window: int = 40
    vpt_threshold: float = 0.3
    fix_lr_factor: float = 0.1
    rounds: int = 3
    jobs: int | None = None

    def __post_init__(self) -> None:
        for kind in self.kinds:
            if kind not in DEFAULT_KINDS:
                raise ConfigError(
                    f"diagnose.kinds: unknown effect kind {kind!r}; the library holds {', '.join(DEFAULT_KINDS)}."
                    + did_you_mean(str(kind), DEFAULT_KINDS)
                )
        counts = ("n_boot", "screen_trajectories", "fit_trajectories", "max_candidates", "shooting_iters", "rounds")
        for name in counts:
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"diagnose.{name} must be >= 1; got {getattr(self, name)}.")
        if self.fit_window < 2 or (self.horizon is not None and self.horizon < 1):
            raise ConfigError(
                f"diagnose.fit_window must be >= 2 and diagnose.horizon >= 1 (or null); got {self.fit_window}, "
                f"{self.horizon}."
            )
        levels = ("min_gain", "null_factor", "min_inclusion", "margin", "min_explained", "structured_factor")
        for name in (*levels, "tolerance", "vpt_threshold", "fix_lr_factor"):
            value = float(getattr(self, name))
            positive = name in ("tolerance", "vpt_threshold", "fix_lr_factor")
            if not math.isfinite(value) or value < 0 or (positive and value == 0):
                raise ConfigError(
                    f"diagnose.{name} must be a finite number {'> 0' if positive else '>= 0'}; got {value}."
                )
        if any(not math.isfinite(float(d)) or float(d) <= 0 for d in self.delays or []):
            raise ConfigError(f"diagnose.delays must be times > 0; got {list(self.delays or [])}.")
        if self.jobs is not None and self.jobs < 1:
            raise ConfigError(f"diagnose.jobs must be >= 1 or null (one per CPU core); got {self.jobs}.")
