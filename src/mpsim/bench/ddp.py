"""Data-parallel throughput: training steps per second with 1 vs several processes (DDP).

Each case is the trainer's own step — `model.training_loss` on one global batch, backward, gradient clip,
Adam — run by P processes that each take 1/P of the batch (`DistContext.shard`, `DistContext.wrap`: the
code `torchrun -m mpsim train` runs). One process is the plain single-process step. Every process count
starts fresh processes (spawned, gloo on CPU, nccl on CUDA with one GPU per process), takes `warmup` steps,
then times `steps` steps between two barriers (CUDA synchronised). Cases:

- ``nbody``: DeltaGN on a kNN graph, one state of N particles per trajectory (global batch `nbody_batch`
  states at N = `nbody_n`, the issue's N = 10⁴): a one-step training step.
- ``mpnode``: MP-NODE on Lorenz10 (10 coupled Lorenz systems), single shooting over `mpnode_steps` rk4 steps
  for a global batch of `mpnode_batch` trajectories (the trainer's default batch).

Throughput is samples (states or trajectories) per second; ``speedup`` is against one process. ``final_loss``
(the last step's loss over the whole global batch) is the same for every process count: the processes do the
same work as one. On a machine with fewer cores than processes × threads the processes share cores, and the
speedup says so.
"""

from __future__ import annotations

import math
import statistics
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
import torch.multiprocessing as mp

from mpsim.bench.common import Suite, resolve_device
from mpsim.errors import ConfigError

if TYPE_CHECKING:
    from mpsim.data.trajectories import Trajectories
    from mpsim.models.base import Model

CASES = ("nbody", "mpnode")


class DDPBench(Suite):
    """Args:
    cases: workloads to time (``nbody``, ``mpnode``).
    processes: process counts to compare (1 is the single-process baseline).
    nbody_n: particles per state.
    nbody_batch: states per global batch.
    nbody_graph: N-body graph (``knn`` or ``hierarchical``).
    mpnode_batch: Lorenz10 trajectories per global batch.
    mpnode_steps: rollout steps per trajectory.
    steps: optimiser steps per timed window.
    repeats: timed windows per case; ``step_s`` is the fastest window's time per step (the machine is shared:
        the slower windows measure the neighbours' load as much as the code), ``median_step_s`` the median.
    warmup: untimed steps first.
    threads: torch threads per process.
    device: ``cpu``, ``cuda`` (one GPU per process) or ``auto``.
    """

    name = "ddp"

    def __init__(
        self,
        cases: Sequence[str] = CASES,
        processes: Sequence[int] = (1, 2),
        nbody_n: int = 10_000,
        nbody_batch: int = 2,
        nbody_graph: str = "knn",
        mpnode_batch: int = 32,
        mpnode_steps: int = 50,
        steps: int = 5,
        repeats: int = 3,
        warmup: int = 1,
        threads: int = 1,
        device: str = "cpu",
    ) -> None:
        unknown = [c for c in cases if c not in CASES]
        if unknown or not cases:
            raise ConfigError(f"bench.cases={list(cases)}: choose from {', '.join(CASES)}.")
        if not processes or min(processes) < 1 or steps < 1 or repeats < 1:
            raise ConfigError(
                f"need bench.processes (a non-empty list), bench.steps and bench.repeats >= 1; got {list(processes)}, "
                f"{steps}, {repeats}."
            )
        self.cases, self.processes = list(cases), sorted(set(int(p) for p in processes))
        self.nbody_n, self.nbody_batch, self.nbody_graph = nbody_n, nbody_batch, nbody_graph
        self.mpnode_batch, self.mpnode_steps = mpnode_batch, mpnode_steps
        self.steps, self.repeats, self.warmup, self.threads = steps, repeats, warmup, threads
        self.device = resolve_device(device)

    def run(self) -> list[dict[str, Any]]:
        rows: list[dict[str, Any]] = []
        for case in self.cases:
            for p in self.processes:
                if self.device.startswith("cuda") and p > torch.cuda.device_count():
                    rows.append(
                        {
                            "case": case,
                            "processes": p,
                            "device": self.device,
                            "note": f"skipped: {p} processes need {p} GPUs, found {torch.cuda.device_count()}",
                        }
                    )
                    continue
                rows.append(self._measure(case, p))
        for row in rows:
            base = next((r for r in rows if r["case"] == row["case"] and r["processes"] == 1 and "step_s" in r), None)
            if base is not None and "step_s" in row:
                row["speedup"] = base["step_s"] / row["step_s"]
        return rows

    def _measure(self, case: str, processes: int) -> dict[str, Any]:
        spec = {
            "case": case,
            "nbody_n": self.nbody_n,
            "nbody_batch": self.nbody_batch,
            "nbody_graph": self.nbody_graph,
            "mpnode_batch": self.mpnode_batch,
            "mpnode_steps": self.mpnode_steps,
            "steps": self.steps,
            "repeats": self.repeats,
            "warmup": self.warmup,
            "threads": self.threads,
            "device": self.device,
        }
        ctx = mp.get_context("spawn")
        queue = ctx.SimpleQueue()
        with tempfile.TemporaryDirectory() as tmp:
            init = (Path(tmp) / "rendezvous").as_uri()
            mp.start_processes(
                _worker, args=(processes, spec, init, queue), nprocs=processes, join=True, start_method="spawn"
            )
        result = queue.get()
        batch = self.nbody_batch if case == "nbody" else self.mpnode_batch
        step_s = min(result["seconds"]) / self.steps
        return {
            "case": case,
            "processes": processes,
            "device": self.device,
            "backend": result["backend"],
            "global_batch": batch,
            "size": f"N={self.nbody_n}" if case == "nbody" else f"Lorenz10, {self.mpnode_steps} steps",
            "step_s": step_s,
            "median_step_s": statistics.median(result["seconds"]) / self.steps,
            "samples_per_s": batch / step_s,
            "final_loss": result["loss"],
        }

    def summarise(self, rows: list[dict[str, Any]]) -> list[str]:
        lines = []
        for case in self.cases:
            sub = [r for r in rows if r["case"] == case and "step_s" in r]
            for r in sub:
                if r["processes"] > 1:
                    eff = r["speedup"] / r["processes"]
                    lines.append(
                        f"- {case}: {r['processes']} processes run {r['samples_per_s']:.3g} samples/s, "
                        f"{r['speedup']:.2f}× one process ({100 * eff:.0f}% parallel efficiency)"
                    )
        return lines


def _build(spec: dict[str, Any], device: torch.device) -> tuple[Model, Trajectories, torch.Tensor, Any]:
    """(model, global batch as Trajectories, its times, loss function) of a case, identical on every rank."""
    from mpsim.data.dataset import fit_normalisation
    from mpsim.data.trajectories import Trajectories
    from mpsim.metrics import LOSSES

    torch.manual_seed(0)
    model: Model
    if spec["case"] == "nbody":
        from mpsim.bench.nbody import uniform_state
        from mpsim.models.deltagn import DeltaGN
        from mpsim.periodic import wrap_positions

        n, b, dt = spec["nbody_n"], spec["nbody_batch"], 0.01
        states = [uniform_state(n, seed=s) for s in range(b)]
        x0 = torch.cat([s[0] for s in states])  # [B, N, 4]
        box = states[0][2]
        x1 = x0.clone()
        x1[..., :2] = wrap_positions(x0[..., :2] + dt * x0[..., 2:], box)  # a drift step
        x = torch.stack([x0, x1], dim=1)  # [B, 2, N, 4]
        data = Trajectories(
            t=torch.tensor([0.0, dt], dtype=torch.float64),
            x=x,
            edge_index=torch.zeros(2, 0, dtype=torch.long),
            meta={"box_size": box},
        )
        model = DeltaGN(graph=spec["nbody_graph"], pairs_per_trajectory=1)
    else:
        from mpsim.models.mpnode import MPNODE
        from mpsim.solvers.odeint import ODESolver
        from mpsim.systems.lorenz import CoupledLorenz

        system = CoupledLorenz(name="lorenz10", n_nodes=10)
        t = torch.linspace(0, 0.05 * spec["mpnode_steps"], spec["mpnode_steps"] + 1, dtype=torch.float64)
        x0 = system.sample_initial_states(spec["mpnode_batch"], torch.Generator().manual_seed(0))
        data = system.simulate(x0, t, rtol=1e-6, atol=1e-8)
        model = MPNODE(3, solver=ODESolver("rk4"))
    model.set_normalisation(*fit_normalisation(data))
    model = model.to(device)
    data = data.to(device, torch.float32)
    return model, data, data.t.to(device=device, dtype=torch.float32), LOSSES["huber"]


def _worker(rank: int, world: int, spec: dict[str, Any], init: str, queue: Any) -> None:
    """One process of a timed case: join the group (several processes), then time the trainer's step."""
    import torch.distributed as torch_dist

    from mpsim.training.distributed import DistContext, teardown

    torch.set_num_threads(int(spec["threads"]))
    device = torch.device(spec["device"])
    if device.type == "cuda":
        device = torch.device("cuda", rank)
        torch.cuda.set_device(device)
    backend = "nccl" if device.type == "cuda" else "gloo"
    if world > 1:
        torch_dist.init_process_group(backend, init_method=init, rank=rank, world_size=world)
    ctx = DistContext(rank=rank, world_size=world, backend=backend if world > 1 else None, device=device)
    model, data, t, loss_fn = _build(spec, device)
    loss_step = ctx.wrap(model)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    idx, weight = ctx.shard(torch.arange(len(data)))
    batch = data.subset(idx.to(data.x.device))

    def step() -> float:
        loss, _ = loss_step(batch, t, loss_fn, 1.0)
        opt.zero_grad(set_to_none=True)
        (loss * weight).backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 500.0)
        opt.step()
        return float(loss.detach())

    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        ctx.barrier()

    loss = math.nan
    for _ in range(spec["warmup"]):
        loss = step()
    seconds = []
    for _ in range(spec["repeats"]):
        sync()
        t0 = time.perf_counter()
        for _ in range(spec["steps"]):
            loss = step()
        sync()
        seconds.append(time.perf_counter() - t0)
    # the last step's loss over the whole global batch: the same number for any process count
    (total,) = ctx.all_sum([loss * len(idx) if weight > 0 else 0.0])
    if rank == 0:
        queue.put({"seconds": seconds, "loss": total / len(data), "backend": backend if world > 1 else "none"})
    teardown(ctx)
