"""Free runs of long measured records (`mpsim.models.freerun`): a driven, damped oscillator (`model=equations`)
simulated open loop from its first samples over records of 10 000 and 100 000 samples, chunked (parareal: all
chunks of all records in one batched rollout per pass) against each record in one rollout, side by side in one
run, with fixed-step RK4 at `substeps` steps per sample in both; and how far apart the two runs end up."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch

from mpsim.bench.common import Suite, timeit
from mpsim.data.segments import whole_records
from mpsim.data.trajectories import Trajectories
from mpsim.models.equations import EquationsModel
from mpsim.models.freerun import FreeRun, free_run
from mpsim.solvers.odeint import ODESolver

SPEC: dict[str, Any] = {
    "states": ["q", "v"],
    "inputs": ["u"],
    "equations": {"q": "v", "v": "(u - c*v - k*q)/m"},
    "params": {"m": 1.0, "c": 0.3, "k": 4.0},
}


def _records(length: int, n_records: int, dt: float) -> tuple[EquationsModel, Trajectories]:
    """The model, and `n_records` records of `length` samples it generated (RK4, 8 steps a sample; positions
    measured, velocities a first guess 20 % off)."""
    model = EquationsModel(2, control_dim=1, spec=SPEC, solver=ODESolver("rk4", step_size=dt / 8)).double()
    model.bind_inputs(["u"])
    model.set_normalisation(torch.zeros(2, dtype=torch.float64), torch.ones(2, dtype=torch.float64))
    t = dt * torch.arange(length, dtype=torch.float64)
    recs = []
    for r in range(n_records):  # a loop over the few records
        u = (torch.sin(1.3 * t + r) + 0.5 * torch.sin(3.1 * t)).reshape(1, length, 1, 1)
        meta = {
            "state_names": ["q", "v"],
            "control_names": ["u"],
            "input_hold": "linear",
            "source": f"r{r}",
            "t0": [0.0],
        }
        empty = Trajectories(t=t, x=torch.zeros(1, length, 1, 2, dtype=torch.float64),
                             edge_index=torch.zeros(2, 0, dtype=torch.long), u=u, meta=meta)  # fmt: skip
        with torch.no_grad():
            x = model.rollout(torch.tensor([[[0.3, 0.0]]], dtype=torch.float64), t, empty.inputs())
        guess = torch.cat([x[..., :1], 0.8 * x[..., 1:]], dim=-1)
        recs.append(Trajectories(t=t, x=guess, edge_index=empty.edge_index, u=u,
                                 meta={**meta, "observed": ["q"], "estimated": {"v": "20 % off"}}))  # fmt: skip
    return model, whole_records(recs)


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
