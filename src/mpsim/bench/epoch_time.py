"""Epoch time at the MP-NODE paper's sizes: what a paper-budget run costs on this machine, measured, not guessed.

Each case is a real `mpsim train` run (a child process, so nothing of one case leaks into the next) at the
paper's trainer settings (`trainer=paper`: batch 128, Adam 1e-3) for a few epochs on the paper's dataset size.
The trainer logs every epoch's training-pass time and wall clock in `metrics.csv`; the first epoch (warm-up,
allocator growth) is dropped and the median of the rest is reported, with the projected time of the paper's
epoch budget (4000 epochs for MP-NODE, 10000 for L2S). Simulating the dataset is not timed: it happens once,
before the first epoch, and is cached under `paths.cache_dir`, where the paper-sized runs find it again.
Each child trains on the bench's `device` (`cpu` by default, also on a machine with a GPU; `device=cuda` times
the GPU), never on whatever `mpsim train`'s `device=auto` would pick.
"""

from __future__ import annotations

import csv
import os
import statistics
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from mpsim.bench.common import Suite, resolve_device
from mpsim.errors import ConfigError

# the quadrotor data of cli/table2.sh and cli/message_size.sh at PAPER=1 (tests/bench/test_epoch_time.py checks it)
_QUAD = ("data.horizon=50", "data.n_val=30", "data.n_test=30", "solver=dopri5")

#: the cases of the paper's tables and figures (system, model, dataset size, epochs of the paper's budget)
PAPER_CASES: tuple[dict[str, Any], ...] = (
    {"name": "gene 4×4 BA (Table 1)", "overrides": ["system=gene_ba_small", "data.n_train=700"], "paper_epochs": 4000},
    {
        "name": "gene 4×4 BA, L2S (Table 1)",
        "overrides": ["system=gene_ba_small", "model=l2s", "data.n_train=700"],
        "paper_epochs": 10000,
    },
    {"name": "Lorenz10 ds=500 (Table 2)", "overrides": ["system=lorenz10", "data.n_train=500"], "paper_epochs": 4000},
    {
        "name": "Kuramoto10 ER ds=500 (Table 2)",
        "overrides": ["system=kuramoto10_er", "data.n_train=500"],
        "paper_epochs": 4000,
    },
    {  # cli/table2.sh PAPER=1: the gene column's target (G_DS=700), finetuned from gene 4×4 or from scratch
        "name": "gene 8×8 BA (Table 2)",
        "overrides": ["system=gene_ba_large", "data.n_train=700"],
        "paper_epochs": 4000,
    },
    {
        "name": "gene 8×8 BA, L2S (Table 2)",
        "overrides": ["system=gene_ba_large", "model=l2s", "data.n_train=700"],
        "paper_epochs": 10000,
    },
    {  # cli/table2.sh and cli/message_size.sh PAPER=1: 50-step records, 30/30 validation/test, dopri5
        "name": "3 quadrotors, m=13, 700 trajectories (Table 2 pre-training, Figure 7)",
        "overrides": [*_QUAD, "system=quad3", "model.message_size=13", "data.n_train=700"],
        "paper_epochs": 4000,
    },
    {
        "name": "6 quadrotors, m=13, ds=500 (Table 2)",
        "overrides": [*_QUAD, "system=quad6", "model.message_size=13", "data.n_train=500"],
        "paper_epochs": 4000,
    },
    {
        "name": "6 quadrotors, L2S, ds=500 (Table 2)",
        "overrides": [*_QUAD, "system=quad6", "model=l2s", "data.n_train=500"],
        "paper_epochs": 10000,
    },
    {  # cli/foundation.sh PAPER=1: 500 trajectories of 10 s at dt 0.1 split 350/150, 100 more for the test
        "name": "pendulum pair (Figure 3a)",
        "overrides": ["system=pendulum2", "data.n_train=350", "data.n_val=150", "data.n_test=100", "data.horizon=100"],
        "paper_epochs": 4000,
    },
)


class EpochTimeBench(Suite):
    """Args:
    cases: list of {name, overrides (mpsim train arguments), paper_epochs, and optionally source: the `src`
        folder of another mpsim checkout, e.g. the commit before a change, whose code then trains that case:
        the same case with and without `source` times a change side by side}; default: `PAPER_CASES`.
    epochs: epochs run per case (the first is dropped as warm-up).
    trainer: the trainer preset (the paper's: `paper`).
    threads: torch threads of each training process (`threads=` of `mpsim train`).
    timeout: seconds allowed per case (data simulation included).
    only: keep the cases whose name contains one of these strings, case-insensitive, with `x` standing for `×`
        (Hydra's command line does not take `×` unquoted), e.g. `bench.only=[8x8,quadrotors]`.
    device: where each training child runs: `cpu`, `cuda` or `auto` (`cuda` when one is available).
    """

    name = "epoch_time"

    def __init__(
        self,
        cases: Sequence[dict[str, Any]] | None = None,
        epochs: int = 6,
        trainer: str = "paper",
        threads: int = 1,
        timeout: float = 1800.0,
        only: Sequence[str] | None = None,
        device: str = "cpu",
    ) -> None:
        self.device = resolve_device(device)
        if epochs < 2:
            raise ConfigError(f"bench.epochs must be >= 2 (the first epoch is warm-up); got {epochs}.")
        self.cases = []
        for c in cases if cases is not None else PAPER_CASES:
            overrides = c.get("overrides")
            if not isinstance(c.get("name"), str) or isinstance(overrides, str) or not isinstance(overrides, Sequence):
                raise ConfigError(f"bench.cases: each case needs a name and a list of overrides; got {c!r}.")
            case = {**dict(c), "overrides": [str(o) for o in overrides]}
            if case.get("source") is not None:
                source = Path(str(case["source"])).expanduser().resolve()
                if not (source / "mpsim" / "__init__.py").is_file():
                    raise ConfigError(
                        f"bench.cases: the source of case {case['name']!r} must be the src folder of an mpsim "
                        f"checkout (holding mpsim/__init__.py); {source} is not. Make one with e.g. "
                        "`git worktree add /tmp/before HEAD~1` and pass source=/tmp/before/src."
                    )
                case["source"] = str(source)
            self.cases.append(case)
        if only is not None:
            if isinstance(only, str):
                only = [only]

            def plain(text: str) -> str:  # "8×8" is typed "8x8"
                return text.replace("×", "x").lower()

            kept = [c for c in self.cases if any(plain(str(o)) in plain(c["name"]) for o in only)]
            if not kept:
                names = ", ".join(repr(c["name"]) for c in self.cases)
                raise ConfigError(f"bench.only={list(only)} matches no case; the cases are: {names}.")
            self.cases = kept
        self.epochs, self.trainer, self.threads, self.timeout = int(epochs), trainer, int(threads), float(timeout)

    def _train(self, overrides: list[str], run_dir: Path, source: str | None = None) -> list[dict[str, float]]:
        cmd = [
            sys.executable,
            "-m",
            "mpsim",
            "train",
            *overrides,
            f"trainer={self.trainer}",
            f"trainer.max_epochs={self.epochs}",
            "trainer.early_stop_patience=0",
            "trainer.progress=false",
            "eval.plots=false",
            "export=false",
            f"threads={self.threads}",
            f"device={self.device}",
            f"hydra.run.dir={run_dir}",
        ]
        env = None
        if source is not None:  # that checkout's mpsim first on the path, ahead of the installed one
            env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (source, os.environ.get("PYTHONPATH")) if p)}
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=self.timeout, env=env)
        if done.returncode != 0:
            tail = (done.stderr or done.stdout).strip().splitlines()[-3:]
            raise RuntimeError(f"`mpsim train {' '.join(overrides)}` failed: {' | '.join(tail)}")
        with open(run_dir / "metrics.csv", newline="") as f:
            return [{k: float(v) for k, v in row.items() if v not in ("", None)} for row in csv.DictReader(f)]

    def run(self) -> list[dict[str, Any]]:
        rows = []
        with tempfile.TemporaryDirectory(prefix="mpsim-epoch-time-") as tmp:
            for i, case in enumerate(self.cases):
                metrics = self._train(list(case["overrides"]), Path(tmp) / f"case{i}", case.get("source"))
                # row 0 is the evaluation before training, row 1 the warm-up epoch: both dropped
                timed = [m for m in metrics if m["epoch"] >= 2]
                train = [m["epoch_time"] for m in timed]
                walls = [
                    b["wall_time"] - a["wall_time"]
                    for a, b in zip(metrics, metrics[1:], strict=False)
                    if b["epoch"] >= 2
                ]
                epoch_s, wall_s = statistics.median(train), statistics.median(walls)
                budget = int(case.get("paper_epochs", 4000))
                rows.append(
                    {
                        "case": case["name"],
                        "device": self.device,
                        "overrides": " ".join(case["overrides"]),
                        "source": case.get("source") or "this checkout",
                        "epochs_timed": len(train),
                        "train_pass_s": round(epoch_s, 4),
                        "epoch_with_eval_s": round(wall_s, 4),
                        "paper_epochs": budget,
                        "paper_budget_h": round(budget * wall_s / 3600, 2),
                    }
                )
        return rows

    def summarise(self, rows: list[dict[str, Any]]) -> list[str]:
        total = sum(r["paper_budget_h"] for r in rows)
        return [
            f"One run of each case at the paper's budget: {total:.1f} h in all on {self.device} with "
            f"{self.threads} thread(s) "
            "(an epoch = one training pass over the dataset plus the per-epoch validation and test rollouts; "
            "median over the timed epochs after a warm-up epoch). Runs on separate cores add up in parallel."
        ]
