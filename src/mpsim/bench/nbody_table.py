"""The paper's Table 2 / Figure 2 comparison from finished runs, with cost measured side by side.

`mpsim bench bench=nbody_table 'bench.runs=[<run dirs or globs>]'` reads every run's ``summary.json``
(`mpsim train` or `mpsim eval` of an N-body model): rollout RMSE at 20 and 200 steps over (x, y, vx, vy)
(positions by minimum image), the paper's energy error |H_k - H_0| / |H_0| at the same steps (from the
model's ``nbody`` report) and the data's own drift. For each run's model configuration it then measures, in
this one process, the cost of a rollout step (graph build included, batch 1), of a training step per state
(forward + backward), and the peak memory of a training step in a fresh process — untrained weights of the
same architecture, since the cost does not depend on them. The published numbers (spec §6; mean over 5
runs of 500k steps at batch 100 on a P100) stand beside each row.
"""

from __future__ import annotations

import functools
import glob
import json
import math
import re
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from mpsim.bench.common import Suite, peak_memory_mb, timeit
from mpsim.bench.nbody import uniform_state
from mpsim.errors import ConfigError, DataError
from mpsim.safeload import SUMMARY_BYTES, load_json

if TYPE_CHECKING:
    from mpsim.models.nbody_base import ParticleModel

NA = math.nan
# (force, model class, graph, N) -> (RMSE@20, energy@20, RMSE@200, energy@200, source)
PAPER: dict[tuple[str, str, str, int], tuple[float, float, float, float, str]] = {
    ("gravity", "DeltaGN", "hierarchical", 100): (0.0016, 2.71e-5, 0.0612, 2.82e-4, "Table 2"),
    ("gravity", "DeltaGN", "hierarchical", 1000): (0.0013, 2.37e-6, 0.0482, 4.22e-5, "Table 2"),
    ("gravity", "HOGN", "full", 100): (2.09e-4, 6.30e-6, 0.0139, 4.41e-5, "Table 2 (bs 50)"),
    ("gravity", "HOGN", "hierarchical", 100): (0.0046, 8.57e-5, 0.1145, 0.0016, "Table 2"),
    ("gravity", "HOGN", "hierarchical", 1000): (0.0023, 4.87e-6, 0.0691, 4.27e-5, "Table 2 (bs 20)"),
    ("gravity", "DeltaGN", "full", 1000): (0.2416, NA, NA, NA, "Table 4: 24 h, bs 4; 200 steps overflowed"),
    ("gravity", "DeltaGN", "knn", 1000): (0.0086, NA, 0.1565, NA, "Table 4: 24 h, bs 4"),
    ("gravity", "DeltaGN", "full", 100): (NA, NA, NA, NA, "Fig. 2 only (≈ hierarchical at N = 100)"),
    ("gravity", "DeltaGN", "knn", 100): (NA, NA, NA, NA, "Fig. 2 only (worse than hierarchical)"),
    ("gravity", "ConstantVelocity", "none", 100): (0.156, NA, 0.98, NA, "spec §6 (1 trajectory)"),
    ("coulomb", "DeltaGN", "full", 100): (0.0045, 0.0086, 0.0684, 0.0584, "Table 1"),
    ("coulomb", "DeltaGN", "hierarchical", 100): (0.0052, 0.0152, 0.1013, 0.0931, "Table 1"),
    ("coulomb", "DeltaGN", "full", 1000): (0.1744, 0.0592, NA, NA, "Table 1 (bs 4); 200 steps overflowed"),
    ("coulomb", "DeltaGN", "hierarchical", 1000): (0.0058, 0.0014, 0.1252, 0.0418, "Table 1"),
}
# Models evaluated at another N than they were trained at: (force, model, graph, trained N, evaluated N) -> as PAPER.
PAPER_TRANSFER: dict[tuple[str, str, str, int, int], tuple[float, float, float, float, str]] = {
    ("gravity", "DeltaGN", "hierarchical", 1000, 100): (
        NA,
        NA,
        0.117,
        2.3e-3,
        "notebook: 1000-trained, 2 test trajectories",
    ),
}


def _particles(system_name: str) -> int | None:
    """N from an N-body system name such as ``nbody1000`` or ``nbody100_coulomb`` (None if it has none)."""
    match = re.match(r"nbody(\d+)", str(system_name))
    return int(match.group(1)) if match else None


def _build(config: dict[str, Any]) -> ParticleModel:  # an N-body model's config (DeltaGN or HOGN)
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    torch.manual_seed(0)
    return instantiate(OmegaConf.create(config), state_dim=4, control_dim=0)


def _state(n: int, states: int, charge: bool) -> tuple[torch.Tensor, torch.Tensor, float]:
    """([S, N, 4] states, [S, N, 2] (mass, charge), box) — uniform positions, random ± charges if asked."""
    xs, nfs = [], []
    for s in range(states):
        x, nf, box = uniform_state(n, seed=s)
        if charge:
            g = torch.Generator().manual_seed(100 + s)
            nf[..., 1] = torch.where(torch.rand(1, n, generator=g) < 0.5, -1.0, 1.0)
        xs.append(x)
        nfs.append(nf)
    return torch.cat(xs), torch.cat(nfs), box


def train_step(config: dict[str, Any], n: int, states: int) -> None:
    """One forward + backward of `states` one-step predictions (the job whose peak memory is measured)."""
    model = _build(config).train()
    x, nf, box = _state(n, states, bool(config.get("charge", False)))
    model.step(x, nf, box, 0.01).pow(2).mean().backward()


class NBodyTable(Suite):
    """Args:
    runs: run directories (or globs) holding summary.json of N-body models, in table order.
    cost_only: ``"<model>:<graph>:<N>"`` entries (model ``deltagn`` or ``hogn``) measured without a run, for
        models too expensive to train here (e.g. ``deltagn:full:1000``); their accuracy cells stay empty.
    measure: measure step time and memory for each run's model (False: accuracy only).
    train_states: states per measured training step.
    repeats: timing repeats.
    """

    name = "nbody_table"

    def __init__(
        self,
        runs: Sequence[str] = (),
        cost_only: Sequence[str] = (),
        measure: bool = True,
        train_states: int = 2,
        repeats: int = 3,
    ) -> None:
        self.runs, self.cost_only, self.measure = list(runs), list(cost_only), measure
        self.train_states, self.repeats = int(train_states), repeats
        self._costs: dict[tuple[str, int], dict[str, float]] = {}

    def run(self) -> list[dict[str, Any]]:
        dirs = [
            Path(p).parent
            for pattern in self.runs
            for p in sorted(glob.glob(str(Path(pattern) / "**" / "summary.json"), recursive=True))
        ]
        rows = [self._row(d) for d in dict.fromkeys(dirs)]
        return [r for r in rows if r is not None] + [self._cost_row(entry) for entry in self.cost_only]

    def _cost_row(self, entry: str) -> dict[str, Any]:
        """A row with only the measured cost of `entry` = "<model>:<graph>:<N>" (not trained)."""
        try:
            name, graph, n = entry.split(":")
            cls = {"deltagn": "DeltaGN", "hogn": "HOGN"}[name]
        except (ValueError, KeyError):
            raise ConfigError(
                f"bench.cost_only entry {entry!r}: expected '<deltagn|hogn>:<graph>:<N>', e.g. 'deltagn:full:1000'."
            ) from None
        config = {"_target_": f"mpsim.models.{name}.{cls}", "graph": graph}
        paper = PAPER.get(("gravity", cls, graph, int(n)), (NA, NA, NA, NA, ""))
        row = {
            "system": f"nbody{n}",
            "model": cls,
            "graph": graph,
            "N": int(n),
            "trained_on": "not trained (cost only)",
            "n_test": 0,
            "rmse20": NA,
            "energy20": NA,
            "rmse200": NA,
            "energy200": NA,
            "data_drift20": NA,
            "data_drift200": NA,
            "n_diverged": 0,
            "ill_conditioned_h0": 0,
            "edges_per_particle": NA,
            "paper_rmse20": paper[0],
            "paper_energy20": paper[1],
            "paper_rmse200": paper[2],
            "paper_energy200": paper[3],
            "paper_source": paper[4],
            "run": "",
        }
        if self.measure:
            row.update(self._cost(config, int(n)))
        return row

    def _row(self, run: Path) -> dict[str, Any] | None:
        path = run / "summary.json"
        fix = "Rerun that run, or leave it out of bench.runs"
        try:
            s = load_json(path, SUMMARY_BYTES, str(path), fix)
        except (json.JSONDecodeError, UnicodeDecodeError) as err:
            raise DataError(f"{path} is not valid JSON ({err}). {fix}.") from None
        model = s.get("model", {})
        report = model.get("nbody")
        if report is None:  # not an N-body model run
            return None
        config = model.get("config", {})
        n = int(s["system"]["n_nodes"])
        hz = s.get("test", {}).get("horizons", {})
        energy, drift = report.get("energy_error", {}), report.get("data_energy_drift", {})
        force = "coulomb" if "coulomb" in str(s["system"]["name"]) else "gravity"
        cls, graph = model.get("model", "?"), report.get("graph", "none")
        trained = s.get("trained_on") or s["system"]["name"]
        trained_n = _particles(trained)
        if trained_n is not None and trained_n != n:  # generalisation to an unseen N
            paper = PAPER_TRANSFER.get((force, cls, graph, trained_n, n), (NA, NA, NA, NA, "—"))
        else:
            paper = PAPER.get((force, cls, graph, n), (NA, NA, NA, NA, ""))
        row = {
            "system": s["system"]["name"],
            "model": cls,
            "graph": graph,
            "N": n,
            "trained_on": trained,
            "n_test": s.get("data", {}).get("n_test", s.get("data", {}).get("test")),
            "rmse20": hz.get("20", {}).get("rmse_raw", NA),
            "energy20": energy.get("20", NA),
            "rmse200": hz.get("200", {}).get("rmse_raw", NA),
            "energy200": energy.get("200", NA),
            "data_drift20": drift.get("20", NA),
            "data_drift200": drift.get("200", NA),
            "n_diverged": s.get("test", {}).get("n_diverged", 0),
            "ill_conditioned_h0": report.get("n_ill_conditioned", 0),
            "edges_per_particle": report.get("edges_per_particle", NA),
            "paper_rmse20": paper[0],
            "paper_energy20": paper[1],
            "paper_rmse200": paper[2],
            "paper_energy200": paper[3],
            "paper_source": paper[4],
            "run": str(run),
        }
        if self.measure and cls != "ConstantVelocity":
            row.update(self._cost(config, n))
        return row

    def _cost(self, config: dict[str, Any], n: int) -> dict[str, float]:
        key = (json.dumps(config, sort_keys=True), n)
        if key not in self._costs:
            model = _build(config)
            charge = bool(config.get("charge", False))
            x1, nf1, box = _state(n, 1, charge)
            model.eval()
            with torch.no_grad():
                roll = timeit(lambda: model.step(x1, nf1, box, 0.01), self.repeats, max_seconds=30)
            xs, nfs, box = _state(n, self.train_states, charge)
            model.train()

            def step() -> None:
                model.zero_grad()
                model.step(xs, nfs, box, 0.01).pow(2).mean().backward()

            tr = timeit(step, self.repeats, max_seconds=60)
            mem = peak_memory_mb(functools.partial(train_step, config, n, self.train_states))
            self._costs[key] = {
                "rollout_step_ms": 1e3 * roll["median_s"],
                "train_ms_per_state": 1e3 * tr["median_s"] / self.train_states,
                "train_peak_mb": mem,
            }
        return self._costs[key]

    def summarise(self, rows: list[dict[str, Any]]) -> list[str]:
        def f(v: Any, digits: int = 2) -> str:
            return "—" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}g}"

        lines = [
            "",
            "**Paper comparison** (ours / published; RMSE over (x, y, vx, vy), energy error |ΔH/H0|; "
            f"cost: rollout step at batch 1, training step per state, peak memory of a {self.train_states}-"
            "state training step):",
            "",
            "| system | model | graph | trained on | RMSE@20 | E@20 | RMSE@200 | E@200 | data drift @20 / @200 "
            "| diverged | step ms | train ms/state | MB | paper source |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in rows:
            lines.append(
                f"| {r['system']} | {r['model']} | {r['graph']} | {r['trained_on']} "
                f"| {f(r['rmse20'], 3)} / {f(r['paper_rmse20'])} | {f(r['energy20'])} / {f(r['paper_energy20'])} "
                f"| {f(r['rmse200'], 3)} / {f(r['paper_rmse200'])} | {f(r['energy200'])} / {f(r['paper_energy200'])} "
                f"| {f(r['data_drift20'])} / {f(r['data_drift200'])} | {r['n_diverged']}/{r['n_test']} "
                f"| {f(r.get('rollout_step_ms', NA), 3)} | {f(r.get('train_ms_per_state', NA), 3)} "
                f"| {f(r.get('train_peak_mb', NA), 3)} | {r['paper_source']} |"
            )
        return lines
