#!/usr/bin/env python3
"""Recordings for the residual loop on latent states (issue 71, cases a and b): generators of our own, numpy only,
no mpsim, built on `cli/latent_cases.py`'s plants and integrator (RK4 at 20 steps a sample, the input held as the
data say, only what a sensor reads recorded, with noise and quantisation). Each case has a clean twin: the same
plant, input and noise draws without the undeclared effects, which must name nothing.

| case | plant | recorded | undeclared effects | what the loop should name |
|---|---|---|---|---|
| a_osc_two | the oscillator of latent_cases (1 Hz, 8.6 samples a period, band-limited multisine held linear) | q + y0 | cubic stiffness k3·q³ and an output offset y0 | CubicStiffness(q) on v, coef k3/m; the offset as a Bias on v, coef k·y0/m (the two are one on a linear plant; with the cubic a remainder 3·k3·y0·q² stays) |
| a_osc_two_noisy | the same, the sensor's noise 5× (0.01) | q + y0 | the same | the same |
| b_tank_leak | the cascaded tanks of latent_cases | lower level h2 | a seepage −λ·h1 from the upper tank (latent) | LinearDamping(h1) on h1, coef λ |

Each writes ``<folder>/<case>/`` with ``<case>.csv`` and ``<case>_clean.csv`` (t, u and the recorded column),
``model.yaml`` (the nominal model: the generator's own equations without the effects) and ``truth.json`` (the
effects as mpsim names them, the sensor's noise, the data keys).

Usage: ``python cli/loop_cases.py <folder> [--seed 0] [--cases a_osc_two,b_tank_leak]``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from latent_cases import CASES as PLANTS  # noqa: E402  (the plants, their inputs and sensors)
from latent_cases import Case, Field, simulate, spec_text  # noqa: E402

K3 = 0.25  # 1/(m²·s²) with m = 1: changes the output by ~10 % of its RMS (40× the noise)
Y0 = 0.03  # the sensor's zero offset (15× the noise)
LEAK = 0.001  # 1/s: the upper tank's seepage (a refit of a1, a2, k absorbs a smaller one: 0.0002 left the held-out error at the noise)


def _osc_two(p: dict[str, float]) -> Field:
    def f(x: np.ndarray, u: float) -> np.ndarray:
        return np.array([x[1], (u - p["c"] * x[1] - p["k"] * x[0] - K3 * x[0] ** 3) / p["m"]])

    return f


def _tank_leak(p: dict[str, float]) -> Field:
    nominal = PLANTS["tanks"].field(p)

    def f(x: np.ndarray, u: float) -> np.ndarray:
        return nominal(x, u) - np.array([LEAK * max(x[0], 0.0), 0.0])

    return f


def _cases() -> dict[str, tuple[Case, Case, dict[str, Any]]]:
    """{name: (the plant with its effects, its clean twin, what mpsim should name and the data keys)}."""
    osc, tanks = PLANTS["oscillator"], PLANTS["tanks"]
    m, k = osc.params["m"], osc.params["k"]
    return {
        "a_osc_two": (
            replace(osc, field=_osc_two, sensor=lambda x: float(x[0]) + Y0),
            osc,
            {
                "effects": [
                    {"kind": "CubicStiffness", "target": "v", "source": "q", "coef": K3 / m},
                    {"kind": "Bias", "target": "v", "coef": k * Y0 / m, "stands_for": f"an output offset y0 = {Y0}"},
                ],
                "keys": ["data.observed=[q]", "data.input_hold=linear", "data.segment=5"],
            },
        ),
        "a_osc_two_noisy": (  # the same with 5× the sensor noise: the one-step residual noise-dominated
            replace(osc, field=_osc_two, sensor=lambda x: float(x[0]) + Y0, noise=5 * osc.noise),
            replace(osc, noise=5 * osc.noise),
            {
                "effects": [
                    {"kind": "CubicStiffness", "target": "v", "source": "q", "coef": K3 / m},
                    {"kind": "Bias", "target": "v", "coef": k * Y0 / m, "stands_for": f"an output offset y0 = {Y0}"},
                ],
                "keys": ["data.observed=[q]", "data.input_hold=linear", "data.segment=5"],
            },
        ),
        "b_tank_leak": (
            replace(tanks, field=_tank_leak),
            tanks,
            {
                "effects": [{"kind": "LinearDamping", "target": "h1", "source": "h1", "coef": LEAK}],
                "keys": ["data.observed=[h2]", "data.input_hold=zoh", "data.segment=200", "eval.init_samples=25"],
            },
        ),
    }


CASES = _cases()


def write_case(out: Path, name: str, seed: int = 0) -> dict[str, Any]:
    """Write case `name` and its clean twin under out/<name>/ (module docstring); returns its truth.json."""
    plant, clean, expected = CASES[name]
    folder = out / name
    folder.mkdir(parents=True, exist_ok=True)
    shares = {}
    for tag, case in (("", plant), ("_clean", clean)):
        data = simulate(case, seed)  # the same seed: the same input and noise draws
        rows = "\n".join(f"{t:.6f},{u:.9g},{y:.9g}" for t, u, y in zip(data["t"], data["u"], data["y"], strict=True))
        (folder / f"{name}{tag}.csv").write_text(f"t,u,{case.column}\n{rows}\n")
        shares[tag or "recording"] = data
    # the tanks' square roots read abs(h): the smoother's sigma points of a 50-sample segment's start reach below an
    # empty tank, where sqrt(h) is NaN (mpsim says so and stops: "clamp a square root's argument")
    (folder / "model.yaml").write_text(
        spec_text(clean).replace("sqrt(h1)", "sqrt(abs(h1))").replace("sqrt(h2)", "sqrt(abs(h2))")
    )
    rec, twin = shares["recording"]["y"], shares["_clean"]["y"]
    info = {
        "case": name,
        "seed": seed,
        "column": plant.column,
        "noise": plant.noise,
        "quantum": plant.quantum,
        "dt": plant.dt,
        "samples": plant.n,
        "effects": expected["effects"],
        "keys": expected["keys"],
        # how much the effects change the recording, against the sensor's noise
        "effect_rms": float(np.sqrt(np.mean((rec - twin) ** 2))),
        "noise_rms": math.sqrt(plant.noise**2 + plant.quantum**2 / 12),
    }
    (folder / "truth.json").write_text(json.dumps(info, indent=1) + "\n")
    return info


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cases", default=",".join(CASES))
    args = parser.parse_args(argv)
    for name in args.cases.split(","):
        if name not in CASES:
            parser.error(f"unknown case {name!r}; choose from {', '.join(CASES)}")
        info = write_case(args.folder, name, args.seed)
        print(
            f"{name}: {info['samples']} samples every {info['dt']:.4g} s; the effects change the recording by "
            f"{info['effect_rms']:.3g} RMS against the sensor's {info['noise_rms']:.3g}"
        )


if __name__ == "__main__":
    main()
