"""The corrected model as equations (issue 72, item 4): the user's spec with every effect the fixed model carries
written into its equations, the effects' coefficients as new parameters at their fitted values — `fixed.yaml`, which
`mpsim train model=equations model.spec=fixed.yaml` reads back as a plain spec (no `model.effects`).

A term of state row d is appended to d's equation, `(<equation>) + <term>`; a parameter drift replaces its
parameter p by `p*(1 + <p>_drift*t)` and a dead zone or saturation its input u by the shaped input, wherever the
equations read them. What the grammar cannot say (a delayed state, a drive or gain with its own phase or value in
every recording) is not written: `written_spec` returns it with the reason, and the caller says so.
"""

from __future__ import annotations

import copy
import math
import re
from typing import Any, cast

from mpsim.effects.base import Effect


def written_spec(model: Any) -> tuple[dict[str, Any], list[str]]:
    """(the spec as plain data with the carried effects written in, [why each effect left out was]) of an
    `EquationsModel`; its own parameters at their current values."""
    spec = copy.deepcopy(model.spec.raw)
    states, inputs = list(model.spec.states), list(model.spec.inputs)
    now = model.parameters_now()
    params: dict[str, Any] = dict(spec.get("params") or {})
    for name in model.spec.learnable:  # the fitted values of the spec's own learnable parameters
        params[name] = _plain(now[name])
    equations: dict[str, str] = {s: str(e) for s, e in (spec.get("equations") or {}).items()}
    learnable = list(spec.get("learnable") or [])
    outputs: dict[str, str] = {o: str(e) for o, e in (spec.get("outputs") or {}).items()}
    left_out: list[str] = []
    shaping: list[Any] = []  # dead zones and saturations, in the order the input passes them
    for effect in model.effects:  # the few carried effects, in order
        kind = type(effect).__name__
        name = _fresh(_snake(kind), effect, states, params, inputs)
        if getattr(effect, "acts_on_parameters", False):  # p -> p*(1 + s*t)
            p = effect.param
            params[f"{p}_drift"] = effect.rate
            learnable.append(f"{p}_drift")
            equations = {s: _replace(e, p, f"({p}*(1 + {p}_drift*t))") for s, e in equations.items()}
            continue
        if kind in ("DeadZone", "InputSaturation"):
            shaping.append(effect)
            continue
        term, values, why = _term(effect, states[effect.source] if effect.source is not None else "", name)
        if term is None:
            left_out.append(f"{effect.describe()}: {why}")
            continue
        target = states[effect.target]
        equations[target] = f"({equations[target]}) + {term}"
        for key, value in values.items():
            params[key] = value
            learnable.append(key)
    # the input passes the first effect first: replaced from the last one, each replacement reads the earlier ones
    for effect in reversed(shaping):
        u = inputs[effect.channel(inputs)]
        key = _fresh(f"{u}_{effect.key}", None, states, params, inputs)
        params[key] = effect.threshold
        learnable.append(key)
        excess = f"(abs({u}) - {key} + abs(abs({u}) - {key}))/2"  # max(|u| − w, 0)
        shaped = f"(sign({u})*{excess})" if type(effect).__name__ == "DeadZone" else f"({u} - sign({u})*{excess})"
        equations = {s: _replace(e, u, shaped) for s, e in equations.items()}
        outputs = {o: _replace(e, u, shaped) for o, e in outputs.items()}
    spec.update(params=params, equations=equations, learnable=learnable)
    if outputs:
        spec["outputs"] = outputs
    return spec, left_out


def _term(effect: Effect, s: str, p: str) -> tuple[str | None, dict[str, Any], str]:
    """(the term in the spec's grammar, its new parameters {name: value}, why not when the term is None)."""
    kind = type(effect).__name__
    coef = [float(c) for c in effect.coef.detach()]
    nodes = getattr(effect, "nodes", None)
    if nodes is not None:  # one coefficient per listed node, zero on the others: a per-node parameter
        value: Any = [0.0] * (max(nodes) + 1)
        for n, c in zip(nodes, coef, strict=True):
            value[n] = c
        if kind not in ("LinearDamping", "QuadraticDrag", "DryFriction", "CubicStiffness", "Bias"):
            return None, {}, "a per-node coupling is not written into equations"
    else:
        value = coef[0]
    if kind == "LinearDamping":
        return f"-{p}*{s}", {p: value}, ""
    if kind == "QuadraticDrag":
        return f"-{p}*{s}*abs({s})", {p: value}, ""
    if kind == "DryFriction":
        return f"-{p}*tanh({s}/{effect.scale!r})", {p: value}, ""
    if kind == "CubicStiffness":
        return f"-{p}*{s}**3", {p: value}, ""
    if kind == "Bias":
        return f"{p}", {p: value}, ""
    if kind == "DiffusiveCoupling":
        return f"{p}*sum_nbr({s}_j - {s})", {p: value}, ""
    if kind in ("SineCoupling", "CosineCoupling"):
        fn, k = ("sin" if kind == "SineCoupling" else "cos"), int(getattr(effect, "harmonic", 1))
        inside = f"{s}_j - {s}" if k == 1 else f"{k}*({s}_j - {s})"
        return f"{p}*sum_nbr({fn}({inside}))", {p: value}, ""
    if kind == "PeriodicForcing" and not getattr(effect, "random_phase", False):
        a, b = coef  # A sin(ωt + φ) = a sin ωt + b cos ωt
        omega = float(cast(Any, effect).log_omega.detach().exp())
        return (
            f"{p}_amplitude*sin({p}_omega*t + {p}_phase)",
            {f"{p}_amplitude": math.hypot(a, b), f"{p}_omega": omega, f"{p}_phase": math.atan2(b, a)},
            "",
        )
    if kind == "DelayedFeedback":
        return None, {}, "a delayed state has no form in the equations' grammar; carry it as model.effects"
    return None, {}, "its value differs per recording (or it has no form in the equations' grammar)"


def _snake(kind: str) -> str:
    return re.sub(r"(?<!^)(?=[A-Z])", "_", kind).lower()


def _fresh(base: str, effect: Effect | None, states: list[str], params: dict[str, Any], inputs: list[str]) -> str:
    """A parameter name for the effect's coefficient: <kind>_<target> (`base` alone without an effect), numbered
    when taken."""
    stem = base if effect is None else f"{base}_{states[effect.target] if effect.target is not None else 'x'}"
    name, k = stem, 2
    while name in params or name in states or name in inputs:
        name, k = f"{stem}_{k}", k + 1
    return name


def _replace(expr: str, name: str, by: str) -> str:
    """`expr` with every whole-word `name` replaced by `by` (not inside longer names, not a neighbour's `name_j`)."""
    return re.sub(rf"(?<![\w.]){re.escape(name)}(?!\w)", by, expr)


def _plain(v: Any) -> Any:
    return float(v.detach()) if v.dim() == 0 else v.detach().double().tolist()
