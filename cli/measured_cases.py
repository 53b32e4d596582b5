#!/usr/bin/env python3
"""Measured-style cases for the residual loop (issue 60), from generators of our own: numpy only, no mpsim.

Each case is a driven mass (states q, v; input u, a force in N) integrated by a fixed-step RK4 at a fine internal
step, the input held zero-order between samples (as a DAC holds it), then sampled and measured: only the position
is recorded, with sensor noise and quantisation, beside the input as it was applied. Each case writes, into the
folder given on the command line, under <case>/:

- ``<case>.csv``        the recording (a wide CSV, one row per sample)
- ``<case>_clean.csv``  its clean twin: the same plant, reference/excitation and noise, without the missing effect
- ``model.yaml``        the nominal model as an equations spec (``inputs: [u]``), its parameters a few % off
- ``truth.json``        the missing effect as mpsim names it (kind, target row, coefficient in d(target)/dt
                        units), the true nominal parameters, the data's settings and the effect's size

| case | plant | missing effect (undeclared) | expected from `mpsim diagnose` |
|---|---|---|---|
| b_axis_coulomb | PD-controlled positioning axis, 1 kHz, encoder | Coulomb friction −Fc·tanh(v/ε) | DryFriction(v), coef Fc/m |
| c_duffing | oscillator driven by a random-phase multisine | cubic stiffness −k3·q³ | CubicStiffness(q) on v, coef k3/m |
| d_input_gain | the linear oscillator, mass known (fixed) | actuator gain g ≠ 1: force g·u | unexplained (no input-gain kind) |
| d_deadzone | the PD axis of b, no Coulomb friction | amplifier dead zone of width d on u | unexplained (not a friction) |

Usage: ``python cli/measured_cases.py <folder> [--seed 0] [--seconds S] [--cases b_axis_coulomb,c_duffing]``.
Deterministic for a seed. `make_case` returns the arrays (and the true states) for tests.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

Accel = Callable[[float, float, float], float]  # (q, v, applied force) -> dv/dt


@dataclass
class Sensor:
    """Position measurement: Gaussian noise of `noise` (m), then rounded to `quantum` (m)."""

    noise: float
    quantum: float

    def read(self, q: float, e: float) -> float:  # e: a standard normal draw
        return round((q + self.noise * e) / self.quantum) * self.quantum


@dataclass
class PD:
    """A sampled PD position loop: u_k = Kp (r_k − y_k) − Kd·v̂_k, v̂ the encoder's backward difference through a
    first-order low-pass (cut-off `fc` Hz), saturated at ±`u_max` and rounded to the DAC's `u_step`."""

    kp: float
    kd: float
    fc: float
    u_max: float
    u_step: float
    reference: np.ndarray  # [n + 1] r_k (m)
    dt: float
    _y: float | None = None
    _v: float = 0.0

    def __call__(self, k: int, y: float) -> float:
        if self._y is not None:
            a = math.exp(-2 * math.pi * self.fc * self.dt)
            self._v = a * self._v + (1 - a) * (y - self._y) / self.dt
        self._y = y
        u = self.kp * (self.reference[k] - y) - self.kd * self._v
        return round(max(-self.u_max, min(self.u_max, u)) / self.u_step) * self.u_step


@dataclass
class Recording:
    """A generated recording: sample times, true states, measured position, applied input."""

    t: np.ndarray  # [n + 1] s
    x: np.ndarray  # [n + 1, 2] true (q, v) at the sample times
    y: np.ndarray  # [n + 1] measured q
    u: np.ndarray  # [n + 1] the input as commanded and recorded (held from t_k to t_k+1)
    extra: dict[str, Any] = field(default_factory=dict)


def run(
    accel: Accel,
    actuator: Callable[[float], float],
    control: Callable[[int, float], float],
    sensor: Sensor,
    noise: np.ndarray,  # [n + 1] standard normal draws of the sensor noise
    dt: float,
    substeps: int,
    x0: tuple[float, float] = (0.0, 0.0),
) -> Recording:
    """Sample k: measure y_k, compute u_k = control(k, y_k), hold actuator(u_k) over [t_k, t_k+1) in `substeps` RK4
    steps of q' = v, v' = accel(q, v, f)."""
    n = len(noise) - 1
    h = dt / substeps
    xs, ys, us = np.empty((n + 1, 2)), np.empty(n + 1), np.empty(n + 1)
    q, v = x0
    for k in range(n + 1):  # a loop in time: the controller closes the loop sample by sample
        xs[k] = q, v
        ys[k] = y = sensor.read(q, float(noise[k]))
        us[k] = u = control(k, y)
        if k == n:
            break
        f = actuator(u)
        for _ in range(substeps):  # fixed-step RK4 of the second-order system, the force held
            a1 = accel(q, v, f)
            q2, v2 = q + 0.5 * h * v, v + 0.5 * h * a1
            a2 = accel(q2, v2, f)
            q3, v3 = q + 0.5 * h * v2, v + 0.5 * h * a2
            a3 = accel(q3, v3, f)
            q4, v4 = q + h * v3, v + h * a3
            a4 = accel(q4, v4, f)
            q, v = q + h / 6 * (v + 2 * v2 + 2 * v3 + v4), v + h / 6 * (a1 + 2 * a2 + 2 * a3 + a4)
    return Recording(np.arange(n + 1) * dt, xs, ys, us)


# ---- excitations ------------------------------------------------------------------------------------------------


def min_jerk_moves(rng: np.random.Generator, n: int, dt: float, span: float = 0.04) -> np.ndarray:
    """[n + 1] a positioning reference: dwells (0.05–0.4 s), smooth minimum-jerk moves of 5–60 mm within ±span
    lasting 0.2–0.5 s, and now and then (one in five) a step of 0.2–1 mm."""
    r = np.zeros(n + 1)
    pos, k = 0.0, 0
    while k <= n:
        dwell = int(rng.uniform(0.05, 0.4) / dt)
        r[k : k + dwell] = pos
        k += dwell
        if rng.random() < 0.2:
            pos = float(np.clip(pos + rng.choice([-1, 1]) * rng.uniform(2e-4, 1e-3), -span, span))
            continue
        target = pos
        while abs(target - pos) < 5e-3 or abs(target - pos) > 0.06:
            target = rng.uniform(-span, span)
        m = int(rng.uniform(0.2, 0.5) / dt)
        s = np.arange(1, m + 1) / m
        r[k : k + m] = (pos + (target - pos) * (10 * s**3 - 15 * s**4 + 6 * s**5))[: max(0, n + 1 - k)]
        pos, k = target, k + m
    return r


def multisine(rng: np.random.Generator, n: int, dt: float, band: tuple[float, float], period: float, rms: float):
    """[n + 1] a random-phase multisine sampled at dt: every line k/period Hz inside `band`, equal amplitudes,
    phases uniform in [0, 2π), scaled to `rms` (N). Periodic with `period` s."""
    lines = np.arange(math.ceil(band[0] * period), math.floor(band[1] * period) + 1) / period
    phases = rng.uniform(0, 2 * np.pi, lines.size)
    t = np.arange(n + 1) * dt
    u = np.cos(2 * np.pi * lines[None, :] * t[:, None] + phases[None, :]).sum(1)
    return u * rms / np.sqrt(np.mean(u**2))


# ---- the cases --------------------------------------------------------------------------------------------------


def _share(term: np.ndarray, total: np.ndarray) -> float:
    """RMS of the missing term over RMS of the whole dv/dt (0 while nothing moves)."""
    scale = float(np.sqrt(np.mean(total**2)))
    return float(np.sqrt(np.mean(term**2))) / scale if scale > 0 else 0.0


# positioning axis (b, d_deadzone): a 2 kg carriage on a ball rail, linear motor, 1 µm encoder at 1 kHz
AXIS = {"m": 2.0, "Fv": 10.0}
AXIS_START = {"m": 2.1, "Fv": 9.5}  # the spec's initial guesses (+5 %, −5 %)
AXIS_DT, AXIS_SUB = 1e-3, 20
AXIS_SENSOR = Sensor(noise=2e-7, quantum=1e-6)
COULOMB = {"Fc": 0.4, "eps": 5e-4}  # N (rail seals and preload); tanh over 0.5 mm/s (the encoder: 1 mm/s per count)
DEADZONE = 0.4  # N: no force below 0.4 N of command, then u ∓ 0.4 N (0.4 % of the 100 N amplifier range)

# driven oscillator (c, d_input_gain): 0.5 kg on a spring, shaker force, laser sensor at 500 Hz
OSC = {"m": 0.5, "c": 2.0, "k": 200.0}  # ω0 = 20 rad/s (3.2 Hz), ζ = 0.1
OSC_START = {"m": 0.52, "c": 1.9, "k": 194.0}  # +4 %, −5 %, −3 %
OSC_DT, OSC_SUB = 2e-3, 10
OSC_SENSOR = Sensor(noise=2e-6, quantum=1e-6)
OSC_EXCITATION = {"band": (1.0, 8.0), "period": 10.0, "rms": 1.0}  # Hz, s, N
DUFFING_K3 = 8.0e4  # N/m³: at the largest displacement (≈ 28 mm) k3·q² is 30 % of k
GAIN = 0.8  # the actuator delivers 80 % of the commanded force


def _axis(seed: int, seconds: float, effect: str | None) -> tuple[Recording, dict[str, Any]]:
    m, fv = AXIS["m"], AXIS["Fv"]
    fc, eps = COULOMB["Fc"], COULOMB["eps"]
    coulomb = effect == "coulomb"

    def accel(q: float, v: float, f: float) -> float:
        return (f - fv * v - (fc * math.tanh(v / eps) if coulomb else 0.0)) / m

    def dead(u: float) -> float:
        return math.copysign(max(abs(u) - DEADZONE, 0.0), u)

    rng = np.random.default_rng(seed)
    n = round(seconds / AXIS_DT)
    reference = min_jerk_moves(rng, n, AXIS_DT)
    noise = rng.standard_normal(n + 1)
    pd = PD(kp=2.0e4, kd=250.0, fc=300.0, u_max=100.0, u_step=1e-4, reference=reference, dt=AXIS_DT)
    actuator = dead if effect == "deadzone" else (lambda u: u)
    rec = run(accel, actuator, pd, AXIS_SENSOR, noise, AXIS_DT, AXIS_SUB)
    rec.extra["reference"] = reference
    v, u = rec.x[:-1, 1], rec.u[:-1]
    applied = np.array([actuator(float(x)) for x in u])
    total = (applied - fv * v - (fc * np.tanh(v / eps) if coulomb else 0.0)) / m
    missing = -fc * np.tanh(v / eps) / m if coulomb else (applied - u) / m
    info = {"share_of_dvdt_rms": _share(missing, total) if effect else 0.0, "v_rms": float(np.sqrt(np.mean(v**2)))}
    return rec, info


def _oscillator(seed: int, seconds: float, effect: str | None) -> tuple[Recording, dict[str, Any]]:
    m, c, k = OSC["m"], OSC["c"], OSC["k"]
    k3 = DUFFING_K3 if effect == "cubic" else 0.0
    gain = GAIN if effect == "gain" else 1.0

    def accel(q: float, v: float, f: float) -> float:
        return (f - c * v - k * q - k3 * q**3) / m

    rng = np.random.default_rng(seed)
    n = round(seconds / OSC_DT)
    u = np.round(multisine(rng, n, OSC_DT, **OSC_EXCITATION), 6)
    noise = rng.standard_normal(n + 1)
    rec = run(accel, lambda f: gain * f, lambda i, y: float(u[i]), OSC_SENSOR, noise, OSC_DT, OSC_SUB)
    q, v, f = rec.x[:-1, 0], rec.x[:-1, 1], rec.u[:-1]
    total = (gain * f - c * v - k * q - k3 * q**3) / m
    missing = -k3 * q**3 / m if effect == "cubic" else (gain - 1) * f / m
    info = {
        "share_of_dvdt_rms": _share(missing, total) if effect else 0.0,
        "q_rms": float(np.sqrt(np.mean(q**2))),
        "q_max": float(np.abs(q).max()),
    }
    return rec, info


def _axis_spec(name: str, what: str) -> dict[str, Any]:
    return {
        "name": name,
        "description": what,
        "states": ["q", "v"],
        "inputs": ["u"],
        "equations": {"q": "v", "v": "(u - Fv*v)/m"},
        "params": dict(AXIS_START),
        "learnable": ["m", "Fv"],
        "nodes": 1,
    }


def _osc_spec(name: str, what: str, learnable: list[str]) -> dict[str, Any]:
    start = {p: (OSC_START[p] if p in learnable else OSC[p]) for p in OSC}
    return {
        "name": name,
        "description": what,
        "states": ["q", "v"],
        "inputs": ["u"],
        "equations": {"q": "v", "v": "(u - c*v - k*q)/m"},
        "params": start,
        "learnable": learnable,
        "nodes": 1,
    }


@dataclass
class Case:
    """One case: how to generate it, its nominal spec, what is missing and how the CSV is laid out."""

    name: str
    generate: Callable[[int, float, str | None], tuple[Recording, dict[str, Any]]]
    effect: str  # the generator's name of the missing effect
    seconds: float  # length of the recording
    spec: dict[str, Any]
    truth_params: dict[str, float]
    missing: dict[str, Any]  # kind as mpsim names it (or null), row, coefficient, physical values
    expected: str  # verdict the loop should give on the recording
    sensor: Sensor
    position_column: str = "q"
    time_column: bool = True  # False: no time column (read with data.dt)
    seed_offset: int = 0


CASES = {
    c.name: c
    for c in (
        Case(
            "b_axis_coulomb",
            _axis,
            "coulomb",
            20.0,
            _axis_spec("b_axis_coulomb", "PD-controlled positioning axis, viscous friction only (learn m, Fv)"),
            dict(AXIS),
            {
                "kind": "DryFriction",
                "target": "v",
                "source": "v",
                "coef": COULOMB["Fc"] / AXIS["m"],
                "units": "m/s² (dv/dt += −coef·tanh(v/ε))",
                "physical": {"Fc_N": COULOMB["Fc"], "eps_m_per_s": COULOMB["eps"]},
            },
            "effects named",
            AXIS_SENSOR,
            position_column="enc_pos",
            seed_offset=0,
        ),
        Case(
            "c_duffing",
            _oscillator,
            "cubic",
            30.0,
            _osc_spec(
                "c_duffing", "multisine-driven mass-spring-damper, linear spring (learn m, c, k)", ["m", "c", "k"]
            ),
            dict(OSC),
            {
                "kind": "CubicStiffness",
                "target": "v",
                "source": "q",
                "coef": DUFFING_K3 / OSC["m"],
                "units": "1/(m²·s²) (dv/dt += −coef·q³)",
                "physical": {"k3_N_per_m3": DUFFING_K3},
            },
            "effects named",
            OSC_SENSOR,
            seed_offset=1,
        ),
        Case(
            "d_input_gain",
            _oscillator,
            "gain",
            30.0,
            _osc_spec(
                "d_input_gain", "multisine-driven mass-spring-damper, mass weighed: fixed (learn c, k)", ["c", "k"]
            ),
            dict(OSC),
            {
                "kind": None,
                "target": "v",
                "source": "u",
                "coef": (GAIN - 1) / OSC["m"],
                "units": "1/kg (dv/dt += coef·u): an input gain, not a kind in mpsim's library",
                "physical": {"gain": GAIN},
            },
            "unexplained structured residual",
            OSC_SENSOR,
            time_column=False,
            seed_offset=2,
        ),
        Case(
            "d_deadzone",
            _axis,
            "deadzone",
            20.0,
            _axis_spec("d_deadzone", "PD-controlled positioning axis, viscous friction only (learn m, Fv)"),
            dict(AXIS),
            {
                "kind": None,
                "target": "v",
                "source": "u",
                "coef": DEADZONE / AXIS["m"],
                "units": "m/s² (applied force sign(u)·max(|u| − d, 0)): a dead zone on the input, not in mpsim's library",
                "physical": {"deadzone_N": DEADZONE},
            },
            "unexplained structured residual",
            AXIS_SENSOR,
            seed_offset=3,
        ),
    )
}


def make_case(name: str, seed: int = 0, seconds: float | None = None) -> dict[str, Any]:
    """{"recording", "clean": Recording, "info", "clean_info": dict} of case `name` (same noise, reference and
    excitation in both; the clean twin lacks the missing effect)."""
    case = CASES[name]
    length = case.seconds if seconds is None else seconds
    rec, info = case.generate(1000 * seed + case.seed_offset, length, case.effect)
    clean, clean_info = case.generate(1000 * seed + case.seed_offset, length, None)
    return {"recording": rec, "clean": clean, "info": info, "clean_info": clean_info}


def write_csv(path: Path, rec: Recording, position: str, time_column: bool, dt: float) -> None:
    cols, fmts = [rec.y, rec.u], ["%.7f", "%.6f"]
    header = f"{position},u"
    if time_column:
        cols, fmts, header = [rec.t, *cols], ["%.4f", *fmts], f"t,{header}"
    comment = "" if time_column else f"# sampled every {dt:g} s from t = 0 (no time column: read with data.dt)\n"
    with open(path, "w") as f:
        f.write(comment + header + "\n")
        np.savetxt(f, np.column_stack(cols), fmt=fmts, delimiter=",")


def _yaml(spec: dict[str, Any]) -> str:
    """The spec as YAML (flow style for the small mappings, numbers as repr: no float formatting surprises)."""

    def value(v: Any) -> str:
        if isinstance(v, dict):
            return "{" + ", ".join(f"{k}: {value(x)}" for k, x in v.items()) + "}"
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return repr(v) if isinstance(v, float) else str(v)

    lines = [f"# {spec['description']}", "# generated by cli/measured_cases.py: parameters are initial guesses"]
    for k, v in spec.items():
        if k == "equations":
            lines += ["equations:"] + [f"  {s}: {e}" for s, e in v.items()]
        elif k != "description":
            lines.append(f"{k}: {value(v)}")
    return "\n".join(lines) + "\n"


def write_case(out: Path, name: str, seed: int = 0, seconds: float | None = None) -> dict[str, Any]:
    """Write case `name` under out/<name>/ (module docstring); returns its truth.json content."""
    case, made = CASES[name], make_case(name, seed, seconds)
    folder = out / name
    folder.mkdir(parents=True, exist_ok=True)
    rec = made["recording"]
    dt = float(rec.t[1] - rec.t[0])
    write_csv(folder / f"{name}.csv", rec, case.position_column, case.time_column, dt)
    write_csv(folder / f"{name}_clean.csv", made["clean"], case.position_column, case.time_column, dt)
    (folder / "model.yaml").write_text(_yaml(case.spec))
    truth = {
        "case": name,
        "seed": seed,
        "recording": f"{name}.csv",
        "clean_twin": f"{name}_clean.csv",
        "spec": "model.yaml",
        "columns": {"q": case.position_column, "u": "u", "time": "t" if case.time_column else None},
        "dt": dt,
        "seconds": float(rec.t[-1]),
        "missing_effect": case.missing,
        "expected_verdict": case.expected,
        "expected_clean": "nothing named (verdict nothing missing, or unexplained with no claim)",
        "nominal_true": case.truth_params,
        "nominal_start": {p: case.spec["params"][p] for p in case.spec["learnable"]},
        "learnable": case.spec["learnable"],
        "sensor": {"noise_m": case.sensor.noise, "quantum_m": case.sensor.quantum},
        "size": made["info"],
        "x0": [float(x) for x in rec.x[0]],
    }
    (folder / "truth.json").write_text(json.dumps(truth, indent=2, ensure_ascii=False) + "\n")
    return truth


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="folder to write the cases into")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--seconds", type=float, default=None, help="override every recording's length")
    parser.add_argument("--cases", default=",".join(CASES), help=f"comma-separated, of {', '.join(CASES)}")
    args = parser.parse_args(argv)
    for name in args.cases.split(","):
        if name not in CASES:
            parser.error(f"unknown case {name!r}; choose from {', '.join(CASES)}")
        truth = write_case(args.out, name, args.seed, args.seconds)
        size = truth["size"]
        print(
            f"{name}: {truth['seconds']:g} s at {1 / truth['dt']:g} Hz; missing term's share of dv/dt RMS "
            f"{size['share_of_dvdt_rms']:.1%}; "
            + ", ".join(f"{k} {v:.3g}" for k, v in size.items() if k != "share_of_dvdt_rms")
        )


if __name__ == "__main__":
    main()
