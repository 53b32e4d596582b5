#!/usr/bin/env python3
"""Recordings whose unmeasured states are no derivative of anything measured, or that a derivative cannot follow
(issue 70, cases c): generators of our own, numpy only, no mpsim. Each integrates its plant by a fixed-step RK4 at
a fine internal step (20 per sample), the input held as the data say, and records only what a sensor reads, with
noise and quantisation:

| case | plant | recorded | latent |
|---|---|---|---|
| tanks | two cascaded tanks, Torricelli outflow, pump voltage a random staircase (held), 1024 samples at 4 s | lower level h2 | upper level h1 |
| oscillator | damped oscillator at 1 Hz sampled at 8.6 samples per period, band-limited multisine force (linear) | position q | velocity v |
| abs_speed | belt drive: first-order drive lag, damped mode, a PRBS staircase voltage (held), 50 Hz | y = abs(s) | d, s, r |

Each case writes, into ``<folder>/<case>/``: ``<case>.csv`` (t, u and the recorded column), ``model.yaml`` (the
generator's own equations and parameters: nothing is missing), ``truth.npz`` (t and every true state) and
``truth.json`` (the states, which are latent, the sensor's noise and quantum). Given a case folder and a run folder,
it compares the run's estimate of the latent states (its `eval.save_predictions` files) with the truth and its free-run
error with the sensor's noise.

Usage: ``python cli/latent_cases.py <folder> [--seed 0] [--cases tanks,oscillator,abs_speed]``; then ``python cli/latent_cases.py <folder>/<case> <run folder>``.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

Field = Callable[[np.ndarray, float], np.ndarray]  # (state [D], input) -> d state / dt
SUBSTEPS = 20


@dataclass(frozen=True)
class Case:
    """A generator: its plant, input, sampling, sensor and spec."""

    states: list[str]
    params: dict[str, float]
    equations: dict[str, str]
    field: Callable[[dict[str, float]], Field]
    sensor: Callable[[np.ndarray], float]  # true state [D] -> the sensor's reading before noise
    column: str  # the recorded column's name
    output: str | None  # the spec's output expression (None: the column is a state)
    dt: float
    n: int
    hold: str  # "zoh" or "linear"
    excite: Callable[[np.random.Generator, int, float], np.ndarray]
    noise: float
    quantum: float
    x0: list[float]


def staircase(rng: np.random.Generator, n: int, low: float, high: float, dwell: tuple[int, int]) -> np.ndarray:
    """[n] random levels in [low, high], each held `dwell` samples (drawn)."""
    out = np.empty(n)
    k = 0
    while k < n:
        span = int(rng.integers(dwell[0], dwell[1] + 1))
        out[k : k + span] = rng.uniform(low, high)
        k += span
    return out


def multisine(rng: np.random.Generator, n: int, dt: float, band: tuple[float, float], rms: float) -> np.ndarray:
    """[n] a random-phase multisine of every line k/(n·dt) Hz inside `band`, scaled to `rms`."""
    t = dt * np.arange(n)
    period = n * dt
    freqs = np.arange(math.ceil(band[0] * period), math.floor(band[1] * period) + 1) / period
    phases = rng.uniform(0, 2 * np.pi, freqs.size)
    u = np.sin(2 * np.pi * freqs[None, :] * t[:, None] + phases).sum(1)
    return u * rms / u.std()


def prbs(rng: np.random.Generator, n: int, clock: int, level: float) -> np.ndarray:
    """[n] ±level, the sign redrawn every `clock` samples."""
    signs = rng.choice([-1.0, 1.0], size=math.ceil(n / clock))
    return level * np.repeat(signs, clock)[:n]


def _tanks(p: dict[str, float]) -> Field:
    def f(x: np.ndarray, u: float) -> np.ndarray:
        h1, h2 = max(x[0], 0.0), max(x[1], 0.0)
        return np.array([-p["a1"] * math.sqrt(h1) + p["k"] * u, p["a1"] * math.sqrt(h1) - p["a2"] * math.sqrt(h2)])

    return f


def _oscillator(p: dict[str, float]) -> Field:
    def f(x: np.ndarray, u: float) -> np.ndarray:
        return np.array([x[1], (u - p["c"] * x[1] - p["k"] * x[0]) / p["m"]])

    return f


def _belt(p: dict[str, float]) -> Field:
    def f(x: np.ndarray, u: float) -> np.ndarray:
        d, s, r = x
        w = p["w0"]
        return np.array([p["alpha"] * (p["k"] * u - d), r, w * w * (d - s) - 2 * p["xi"] * w * r])

    return f


CASES: dict[str, Case] = {
    "tanks": Case(
        states=["h1", "h2"],
        params={"a1": 0.04, "a2": 0.045, "k": 0.02},
        equations={"h1": "-a1*sqrt(h1) + k*u", "h2": "a1*sqrt(h1) - a2*sqrt(h2)"},
        field=_tanks,
        sensor=lambda x: float(x[1]),
        column="h2",
        output=None,
        dt=4.0,
        n=1024,
        hold="zoh",
        excite=lambda rng, n, dt: staircase(rng, n, 2.0, 8.0, (8, 25)),
        noise=0.01,
        quantum=10 / 4095,
        x0=[4.0, 3.0],
    ),
    "oscillator": Case(
        states=["q", "v"],
        params={"m": 1.0, "c": 0.6, "k": (2 * math.pi) ** 2},
        equations={"q": "v", "v": "(u - c*v - k*q)/m"},
        field=_oscillator,
        sensor=lambda x: float(x[0]),
        column="q",
        output=None,
        dt=1 / 8.6,
        n=4000,
        hold="linear",
        excite=lambda rng, n, dt: multisine(rng, n, dt, (0.3, 1.6), 10.0),
        noise=0.002,
        quantum=0.0005,
        x0=[0.0, 0.0],
    ),
    "abs_speed": Case(
        states=["d", "s", "r"],
        params={"alpha": 6.7, "k": 1.8, "w0": 20.5, "xi": 0.32},
        equations={"d": "alpha*(k*u - d)", "s": "r", "r": "w0**2*(d - s) - 2*xi*w0*r"},
        field=_belt,
        sensor=lambda x: abs(float(x[1])),
        column="y",
        output="abs(s)",
        dt=0.02,
        n=1500,
        hold="zoh",
        excite=lambda rng, n, dt: prbs(rng, n, 5, 1.0),
        noise=0.01,
        quantum=10 / 4095,
        x0=[0.0, 0.0, 0.0],
    ),
}


def simulate(case: Case, seed: int = 0) -> dict[str, np.ndarray]:
    """{"t", "u", "x" [n, D] true states, "y" the recorded column} of `case` (deterministic for a seed)."""
    rng = np.random.default_rng(seed)
    u = case.excite(rng, case.n, case.dt)
    f = case.field(case.params)
    h = case.dt / SUBSTEPS
    x = np.array(case.x0, dtype=float)
    xs = np.empty((case.n, len(case.states)))
    for k in range(case.n):  # a loop over the samples of the reference integrator
        xs[k] = x
        if k + 1 == case.n:
            break
        for j in range(SUBSTEPS):
            if case.hold == "zoh":
                a = b = c = u[k]
            else:
                a, b, c = (u[k] + (u[k + 1] - u[k]) * (j + s) / SUBSTEPS for s in (0.0, 0.5, 1.0))
            k1 = f(x, a)
            k2 = f(x + h / 2 * k1, b)
            k3 = f(x + h / 2 * k2, b)
            k4 = f(x + h * k3, c)
            x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    readings = np.array([case.sensor(row) for row in xs]) + case.noise * rng.standard_normal(case.n)
    y = np.round(readings / case.quantum) * case.quantum
    return {"t": case.dt * np.arange(case.n), "u": u, "x": xs, "y": y}


def spec_text(case: Case) -> str:
    lines = [f"states: [{', '.join(case.states)}]", "inputs: [u]"]
    if case.output:
        lines.append(f"outputs: {{{case.column}: {case.output}}}")
    lines.append("equations:")
    lines += [f"  {s}: {case.equations[s]}" for s in case.states]
    lines.append("params: {" + ", ".join(f"{k}: {v!r}" for k, v in case.params.items()) + "}")
    return "\n".join(lines) + "\n"


def write_case(out: Path, name: str, seed: int = 0) -> dict[str, Any]:
    """Write case `name` under out/<name>/ (module docstring); returns its truth.json content."""
    case = CASES[name]
    data = simulate(case, seed)
    folder = out / name
    folder.mkdir(parents=True, exist_ok=True)
    rows = "\n".join(f"{t:.6f},{u:.9g},{y:.9g}" for t, u, y in zip(data["t"], data["u"], data["y"], strict=True))
    (folder / f"{name}.csv").write_text(f"t,u,{case.column}\n{rows}\n")
    (folder / "model.yaml").write_text(spec_text(case))
    np.savez(folder / "truth.npz", t=data["t"], x=data["x"])
    latent = [s for s in case.states if case.output is not None or s != case.column]
    info = {
        "case": name,
        "seed": seed,
        "states": case.states,
        "latent": latent,
        "column": case.column,
        "noise": case.noise,
        "quantum": case.quantum,
        "input_hold": case.hold,
        "dt": case.dt,
        "samples": case.n,
        "spread": {s: float(data["x"][:, i].std()) for i, s in enumerate(case.states)},
    }
    (folder / "truth.json").write_text(json.dumps(info, indent=1) + "\n")
    return info


def score(case_dir: Path, run_dir: Path) -> dict[str, Any]:
    """The run's latent estimate (the test split it saved, `eval.save_predictions`) against the truth, per latent
    state (RMSE, and as a share of the state's spread), and its free-run error against the sensor's noise."""
    info = json.loads((case_dir / "truth.json").read_text())
    truth = np.load(case_dir / "truth.npz")
    saved = np.load(run_dir / "test.npz")
    meta = json.loads(str(saved["meta"]))
    names = meta["state_names"]
    starts = [float(e["t0"]) for e in meta.get("segments", [{"t0": 0.0}] * saved["x"].shape[0])]
    out: dict[str, Any] = {"case": info["case"], "latent": {}}
    for s in info["latent"]:
        i, j = names.index(s), info["states"].index(s)
        errs = []
        for b, t0 in enumerate(starts):  # a loop over the few test trajectories
            times = t0 + saved["t"]
            want = np.interp(times, truth["t"], truth["x"][:, j])
            errs.append(saved["x"][b, :, 0, i] - want)
        rmse = float(np.sqrt(np.mean(np.concatenate(errs) ** 2)))
        out["latent"][s] = {"rmse": rmse, "share_of_spread": rmse / info["spread"][s]}
    summary = json.loads((run_dir / "summary.json").read_text())
    free = summary.get("freerun") or {}
    noise = math.sqrt(info["noise"] ** 2 + info["quantum"] ** 2 / 12)
    rmse = [r["channels"][info["column"]]["rmse"] for r in free.get("records", [])]
    out["freerun_rmse"] = rmse
    out["sensor_noise"] = noise
    out["estimated_how"] = summary.get("test", {}).get("estimated", {})
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("run", type=Path, nargs="?", help="with score: the run's folder")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cases", default=",".join(CASES))
    args = parser.parse_args(argv)
    if args.run is not None:  # score <case dir> <run dir>
        print(json.dumps(score(args.folder, args.run), indent=1))
        return
    for name in args.cases.split(","):
        info = write_case(args.folder, name.strip(), args.seed)
        print(f"{name}: {info['samples']} samples every {info['dt']:.4g} s, latent {info['latent']}")


if __name__ == "__main__":
    main()
