"""Free runs of long measured records (`mpsim.models.freerun`): a driven, damped oscillator (`model=equations`)
simulated open loop from its first samples over records of 10 000 and 100 000 samples, chunked (parareal: all
chunks of all records in one batched rollout per pass) against each record in one rollout, side by side in one
run, with fixed-step RK4 at `substeps` steps per sample in both; and how far apart the two runs end up."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from mpsim.bench.common import Suite, timeit
from mpsim.data.segments import whole_records
from mpsim.data.trajectories import Trajectories
from mpsim.models.equations import EquationsModel
from mpsim.models.freerun import FreeRun, free_run

SPEC: dict[str, Any] = {
    "states": ["q", "v"],
    "inputs": ["u"],
    "equations": {"q": "v", "v": "(u - c*v - k*q)/m"},
    "params": {"m": 1.0, "c": 0.3, "k": 4.0},
}


def _records(length: int, n_records: int, dt: float) -> tuple[EquationsModel, Trajectories]:
    """The model, and `n_records` records of `length` samples of its equations (a numpy RK4 at 8 steps a sample,
    the input linear between samples; positions measured, velocities a first guess 20 % off)."""
    model = EquationsModel(2, control_dim=1, spec=SPEC).double()
    model.bind_inputs(["u"])
    model.set_normalisation(torch.zeros(2, dtype=torch.float64), torch.ones(2, dtype=torch.float64))
    p = SPEC["params"]
    t = dt * np.arange(length)
    recs = []
    for r in range(n_records):  # a loop over the few records
        u = np.sin(1.3 * t + r) + 0.5 * np.sin(3.1 * t)
        x = _rk4(lambda q, v, f: (v, (f - p["c"] * v - p["k"] * q) / p["m"]), u, dt, 8)
        meta = {"state_names": ["q", "v"], "control_names": ["u"], "input_hold": "linear", "source": f"r{r}",
                "t0": [0.0], "observed": ["q"], "estimated": {"v": "20 % off"}}  # fmt: skip
        guess = torch.tensor(np.stack([x[:, 0], 0.8 * x[:, 1]], -1)).reshape(1, length, 1, 2)
        recs.append(Trajectories(t=torch.tensor(t), x=guess, edge_index=torch.zeros(2, 0, dtype=torch.long),
                                 u=torch.tensor(u).reshape(1, length, 1, 1), meta=meta))  # fmt: skip
    return model, whole_records(recs)


def _rk4(f: Any, u: np.ndarray, dt: float, substeps: int) -> np.ndarray:
    """[T, 2] the states of q' = v, v' = a(q, v, u) from (0.3, 0), classic RK4 at dt/substeps, u linear between
    samples (a loop over time steps: the reference run the bench's records come from)."""
    h, q, v = dt / substeps, 0.3, 0.0
    out = np.empty((len(u), 2))
    for k in range(len(u)):
        out[k] = q, v
        if k + 1 == len(u):
            break
        for j in range(substeps):
            a, b, c = (u[k] + (u[k + 1] - u[k]) * (j + s) / substeps for s in (0.0, 0.5, 1.0))
            k1 = f(q, v, a)
            k2 = f(q + h / 2 * k1[0], v + h / 2 * k1[1], b)
            k3 = f(q + h / 2 * k2[0], v + h / 2 * k2[1], b)
            k4 = f(q + h * k3[0], v + h * k3[1], c)
            q += h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
            v += h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
    return out


class FreeRunBench(Suite):
    """Wall time of a free run of `n_records` records per length, chunked (`chunk` samples) and whole."""

    name = "freerun"

    def __init__(
        self,
        lengths: Sequence[int] = (10_000, 100_000),
        n_records: int = 1,
        dt: float = 0.05,
        chunk: int = 1000,
        substeps: int = 4,
        repeats: int = 3,
    ) -> None:
        self.lengths, self.n_records, self.dt = list(lengths), int(n_records), float(dt)
        self.chunk, self.substeps, self.repeats = int(chunk), int(substeps), int(repeats)

    def run(self) -> list[dict[str, Any]]:
        rows = []
        for length in self.lengths:  # a loop over the few record lengths
            model, records = _records(length, self.n_records, self.dt)
            runs = {mode: self._timed(model, records, mode) for mode in ("chunked", "whole")}
            gap = float((runs["chunked"][1].pred - runs["whole"][1].pred).abs().max())
            for mode, (timing, run) in runs.items():
                rows.append(
                    {
                        "samples": length,
                        "records": self.n_records,
                        "mode": mode,
                        "passes": run.passes,
                        **timing,
                        "fit_q": run.scores[0]["q"]["fit"],
                        "max_abs_diff": gap,
                    }
                )
        return rows

    def _timed(self, model: EquationsModel, records: Trajectories, mode: str) -> tuple[dict[str, float], FreeRun]:
        chunk = self.chunk if mode == "chunked" else 10**12
        out: list[FreeRun] = []
        timing = timeit(
            lambda: out.append(free_run(model, records, chunk=chunk, substeps=self.substeps)),
            repeats=self.repeats,
            warmup=0,
            max_seconds=60.0,
        )
        return timing, out[-1]

    def summarise(self, rows: list[dict[str, Any]]) -> list[str]:
        notes = []
        for length in self.lengths:
            pair = {r["mode"]: r for r in rows if r["samples"] == length}
            if len(pair) == 2:
                ratio = pair["whole"]["median_s"] / pair["chunked"]["median_s"]
                notes.append(
                    f"- {length:,} samples: chunked {pair['chunked']['median_s']:.2f} s ({pair['chunked']['passes']} "
                    f"passes) vs whole {pair['whole']['median_s']:.2f} s: {ratio:.1f}× faster; the two runs differ "
                    f"by at most {pair['chunked']['max_abs_diff']:.2g}."
                )
        return notes
