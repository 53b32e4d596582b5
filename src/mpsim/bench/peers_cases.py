"""The cases of `mpsim bench bench=peers` (issue 61): one line each, with its truth as the scorecard judges it.

A case is its specs' stem (`<stem>_data.yaml`, `<stem>_model.yaml` in `bench.specs`), the effects the recipe adds
to the data (the YAML list `cli/diagnose_cases.sh` passes as `system.effects=...`, copied as it stands) and its
truth: (kind, row, reported key, true value, bound), `UNEXPLAINED` (outside the library) or None (nothing to name).
A coupling's harmonic k > 1 is part of its kind ("SineCoupling(k=2)"), as in the scorecard's `TRUTH`. A value not
known yet is `TODO` (the row says so instead of judging); a case whose spec files are not there says *spec
missing* (the suite goes on with the others).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from mpsim import effects as fx
from mpsim.errors import ConfigError

UNEXPLAINED = "unexplained"
#: a value still to fill in (truth or effect argument): the case's row says "TODO" instead of a verdict
TODO = math.nan
Truth = tuple[str, str, str, float, float] | str | None


@dataclass(frozen=True)
class PeerCase:
    """One scorecard case: how its data are made and what they hold.

    Attributes:
        stem: the specs' stem: `<stem>_data.yaml` (the data) and `<stem>_model.yaml` (the nominal model).
        effects: the recipe's `system.effects` as YAML (`[{_target_: mpsim.effects.X, ...}]`; "[]": none).
        truth: (kind, row, reported key, true value, bound), `UNEXPLAINED` or None.
        recipe: the case is in `cli/diagnose_cases.sh` (its mpsim run can exist); else a twin only PySINDy runs.
        params: overrides of the data spec's parameters (a clean twin of an effect written into the equations).
    """

    stem: str
    effects: str = "[]"
    truth: Truth = None
    recipe: bool = True
    params: dict[str, Any] = field(default_factory=dict)

    @property
    def data(self) -> str:
        return f"{self.stem}_data.yaml"

    @property
    def model(self) -> str:
        return f"{self.stem}_model.yaml"

    @property
    def text(self) -> str:
        """The truth as the scorecard writes it: `SineCoupling(theta, k=2) coef 0.25`."""
        if self.truth is None:
            return "nothing"
        if not isinstance(self.truth, tuple):
            return "unexplained (outside the library)"
        kind, row, key, value, _ = self.truth
        base, _, k = kind.partition("(")
        number = "TODO" if math.isnan(value) else f"{value:.4g}"
        return f"{base}({row}{', ' + k.rstrip(')') if k else ''}) {key} {number}"

    @property
    def todo(self) -> bool:
        """A value of the truth or of the effects is still `TODO`."""
        fields = self.truth if isinstance(self.truth, tuple) else ()
        unknown = [v for v in fields if (isinstance(v, float) and math.isnan(v)) or v == "TODO"]
        return bool(unknown) or "TODO" in self.effects

    def missing(self, specs: Path) -> list[str]:
        """The spec files of this case that are not in `specs`."""
        return [f for f in (self.data, self.model) if not (specs / f).is_file()]

    def make_effects(self) -> list[fx.Effect]:
        """The effects added to the data, built from `effects` as Hydra would (`_target_`: mpsim.effects.<Name>)."""
        out = []
        for cfg in yaml.safe_load(self.effects) or []:
            args = dict(cfg)
            target = str(args.pop("_target_", ""))
            cls = getattr(fx, target.rsplit(".", 1)[-1], None) if target.startswith("mpsim.effects.") else None
            if cls is None:
                raise ConfigError(f"peers case {self.stem}: effect _target_ {target!r} is not mpsim.effects.<Name>.")
            out.append(cls(**args))
        return out


_LAG = -0.4 * math.sin(0.25)
_DAMP = "[{_target_: mpsim.effects.LinearDamping, coef: 0.3, target: v}]"
_DRIVE = "[{_target_: mpsim.effects.PeriodicForcing, amplitude: 1.5, omega: 3.1, phase: 0.0, target: v, random_phase: true, phase_seed: 0}]"
_FRICTION = "[{_target_: mpsim.effects.DryFriction, coef: 0.5, target: v, scale: 0.001}]"
_HARM2 = "[{_target_: mpsim.effects.SineCoupling, coef: 0.25, target: theta, harmonic: 2}]"
# fmt: off
#: every case, one line each: name: PeerCase(spec stem, the recipe's system.effects, truth, ...), the effects copied
#: from cli/diagnose_cases.sh (a value not known yet would be TODO).
CASES: dict[str, PeerCase] = {
    "a_damped": PeerCase("a_chain", _DAMP, ("LinearDamping", "v", "coef", 0.3, 0.10)),
    "a_undamped": PeerCase("a_chain"),
    "b_vdp": PeerCase("b_vdp", _DRIVE, ("PeriodicForcing", "v", "omega", 3.1, 0.03)),
    "c_kuramoto_lag": PeerCase("c_kuramoto_lag", "[]", ("CosineCoupling", "theta", "coef", _LAG, 0.10)),
    "d_chain_friction": PeerCase("d_chain_friction", _FRICTION, ("DryFriction", "v", "coef", 0.5, 0.10)),
    "e_pendulum_sin2": PeerCase("e_pendulum_sin2", "[]", UNEXPLAINED),
    "f_kuramoto_harm2": PeerCase("f_kuramoto_harm2", _HARM2, ("SineCoupling(k=2)", "theta", "coef", 0.25, 0.10)),
    # issue 61's cases
    "g_delay": PeerCase("g_delay", "[{_target_: mpsim.effects.DelayedFeedback, coef: -0.8, delay: 0.125, target: omega}]", ("DelayedFeedback", "omega", "delay", 0.125, 0.10)),
    "g_delay_clean": PeerCase("g_delay"),
    "h_drift": PeerCase("h_drift", "[]", ("ParameterDrift", "v", "s", 0.04, 0.10)),
    "h_drift_clean": PeerCase("h_drift", params={"s": 0.0}),
    "i_bias": PeerCase("i_bias", "[{_target_: mpsim.effects.Bias, coef: 0.1, target: x}]", ("Bias", "x", "coef", 0.1, 0.10)),
    "i_bias_clean": PeerCase("i_bias"),
    "j_semieuler": PeerCase("j_semieuler", "[{_target_: mpsim.effects.LinearDamping, coef: 0.15, target: v}]", ("LinearDamping", "v", "coef", 0.15, 0.10)),
    "j_semieuler_clean": PeerCase("j_semieuler"),
    "k_chaos_drive": PeerCase("k_chaos_drive", "[{_target_: mpsim.effects.PeriodicForcing, amplitude: 4.0, omega: 7.0, phase: 0.0, target: y, random_phase: true, phase_seed: 0}]", ("PeriodicForcing", "y", "omega", 7.0, 0.03)),
    "k_chaos_drive_clean": PeerCase("k_chaos_drive"),
    "l_chain_node": PeerCase("l_chain_node", "[]", ("LinearDamping", "v", "coef", 0.3, 0.10)),
    "l_chain_node_clean": PeerCase("l_chain_node", params={"c": [0.0, 0.0, 0.0, 0.0]}),
    # clean twins the recipe lacks (PySINDy only; `twins=true`)
    "b_vdp_clean": PeerCase("b_vdp", recipe=False),
    "c_kuramoto_clean": PeerCase("c_kuramoto_lag", params={"alpha": 0.0}, recipe=False),
    "d_chain_clean": PeerCase("d_chain_friction", recipe=False),
    "e_pendulum_clean": PeerCase("e_pendulum_sin2", params={"b": 0.0}, recipe=False),
    "f_kuramoto_clean": PeerCase("f_kuramoto_harm2", recipe=False),
}
# fmt: on
#: the cases of the recipe, and the clean twins only PySINDy runs (`twins=true`)
RECIPE_CASES = [name for name, case in CASES.items() if case.recipe]
EXTRA_TWINS = [name for name, case in CASES.items() if not case.recipe]
