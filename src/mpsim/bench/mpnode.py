"""MP-NODE rollout cost: forward and forward+backward time of one batch against graph size and batch size.

Shows that a rollout is batched over trajectories and nodes (time per node-trajectory falls as the batch
grows; no Python loop over nodes or edges) and how the cost grows with N on a complete graph (E = N(N−1)).
Beside each case, timed in the same run with the same weights: the messages aggregated over the edge list
(`model.dense_max_nodes=0`) instead of by the dense adjacency product small graphs use (`graph=ba` is the gene
systems' BA(N, N/2), half of all pairs connected), and the rollout through torchdiffeq's `odeint` as is
(`solver.stacked=false`, whose backward copies the whole [T, ...] gradient once per output), and the node MLP
with torch's own `nn.Tanh` in place of `layers.Tanh` (2σ(2x) − 1 on the CPU). Their ratios to the default are
what each saves.
"""

from __future__ import annotations

import copy
import functools
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from mpsim.bench.common import Suite, scaling_exponent, timeit
from mpsim.data.trajectories import Inputs
from mpsim.errors import ConfigError
from mpsim.graphs.topology import barabasi_albert, chain, complete
from mpsim.models.layers import Tanh
from mpsim.models.mpnode import MPNODE
from mpsim.solvers.odeint import ODESolver

GRAPHS = {"chain": chain, "complete": complete, "ba": lambda n: barabasi_albert(n, max(1, n // 2))}


def with_torch_tanh(model: nn.Module) -> nn.Module:
    """A copy of `model` (same weights) whose `layers.Tanh` activations are torch's own `nn.Tanh`."""
    clone = copy.deepcopy(model)
    for module in list(clone.modules()):
        for name, child in module.named_children():
            if isinstance(child, Tanh):
                setattr(module, name, nn.Tanh())
    return clone


class MPNODEBench(Suite):
    """Args:
    nodes: graph sizes N.
    batches: trajectories per batch B.
    graph: chain, complete or ba (BA(N, N/2), the gene systems' graphs).
    steps: output steps T − 1 of the rollout (fixed-step rk4, one step per output, so every case does the
        same number of vector-field evaluations and times compare like for like).
    repeats: timing repeats per case.
    """

    name = "mpnode"

    def __init__(
        self,
        nodes: Sequence[int] = (2, 10, 30, 100),
        batches: Sequence[int] = (1, 32, 128),
        graph: str = "chain",
        steps: int = 50,
        repeats: int = 3,
    ) -> None:
        if graph not in GRAPHS:
            raise ConfigError(f"bench.graph must be one of {sorted(GRAPHS)}; got {graph!r}.")
        self.nodes, self.batches, self.graph, self.steps, self.repeats = (
            list(nodes),
            list(batches),
            graph,
            steps,
            repeats,
        )

    def run(self) -> list[dict[str, Any]]:
        torch.manual_seed(0)
        model = MPNODE(3, solver=ODESolver("rk4"))
        edges = MPNODE(3, solver=ODESolver("rk4"), dense_max_nodes=0)  # the same weights, edge-list aggregation
        plain = MPNODE(3, solver=ODESolver("rk4", stacked=False))  # the same weights, torchdiffeq's odeint as is
        edges.load_state_dict(model.state_dict())
        plain.load_state_dict(model.state_dict())
        torch_tanh = with_torch_tanh(model)
        t = torch.linspace(0, 0.05 * self.steps, self.steps + 1)
        rows = []
        for n in self.nodes:
            inputs = Inputs(GRAPHS[self.graph](n))
            for b in self.batches:
                x0 = torch.randn(b, n, 3)

                def forward(x0=x0, inputs=inputs):
                    with torch.no_grad():
                        model.rollout(x0, t, inputs)

                def backward(x0=x0, inputs=inputs, model=model):
                    model.zero_grad()
                    model.rollout(x0, t, inputs).pow(2).mean().backward()

                fwd, bwd = timeit(forward, self.repeats), timeit(backward, self.repeats)
                listed = timeit(functools.partial(backward, x0, inputs, edges), self.repeats)
                odeint = timeit(functools.partial(backward, x0, inputs, plain), self.repeats)
                tanh = timeit(functools.partial(backward, x0, inputs, torch_tanh), self.repeats)
                rows.append(
                    {
                        "graph": self.graph,
                        "N": n,
                        "E": int(inputs.edge_index.shape[1]),
                        "B": b,
                        "steps": self.steps,
                        "forward_s": fwd["median_s"],
                        "fwd_bwd_s": bwd["median_s"],
                        "edge_list_fwd_bwd_s": listed["median_s"],
                        "dense_speedup": listed["median_s"] / bwd["median_s"],
                        "odeint_fwd_bwd_s": odeint["median_s"],
                        "stacked_speedup": odeint["median_s"] / bwd["median_s"],
                        "torch_tanh_fwd_bwd_s": tanh["median_s"],
                        "tanh_speedup": tanh["median_s"] / bwd["median_s"],
                        "us_per_node_traj_step": 1e6 * bwd["median_s"] / (n * b * self.steps),
                    }
                )
        return rows

    def summarise(self, rows: list[dict[str, Any]]) -> list[str]:
        lines = []
        for b in self.batches:
            sub = [r for r in rows if r["B"] == b]
            k = scaling_exponent([r["N"] for r in sub], [r["fwd_bwd_s"] for r in sub])
            lines.append(f"- B={b}: forward+backward time ∝ N^{k:.2f} over N = {sub[0]['N']}…{sub[-1]['N']}")
        lines.append(
            f"- {self.graph} graph, B={max(self.batches)}: edge-list aggregation / dense adjacency product, "
            "forward+backward: "
            + ", ".join(
                f"N={r['N']} (E={r['E']}) {r['dense_speedup']:.2f}×" for r in rows if r["B"] == max(self.batches)
            )
        )
        lines.append(
            f"- {self.graph} graph, B={max(self.batches)}: torchdiffeq's odeint as is / stacked outputs, "
            f"forward+backward over {self.steps} steps: "
            + ", ".join(f"N={r['N']} {r['stacked_speedup']:.2f}×" for r in rows if r["B"] == max(self.batches))
        )
        lines.append(
            f"- {self.graph} graph, B={max(self.batches)}: torch's nn.Tanh / layers.Tanh (2σ(2x) − 1), "
            "forward+backward: "
            + ", ".join(f"N={r['N']} {r['tanh_speedup']:.2f}×" for r in rows if r["B"] == max(self.batches))
        )
        small, large = min(self.batches), max(self.batches)
        for n in self.nodes if small < large else ():
            a = next(r for r in rows if r["N"] == n and r["B"] == small)
            c = next(r for r in rows if r["N"] == n and r["B"] == large)
            ratio = a["us_per_node_traj_step"] / c["us_per_node_traj_step"]
            lines.append(
                f"- N={n}: batching {large} trajectories is {ratio:.1f}× cheaper per node-trajectory than {small}"
            )
        return lines

    def plot(self, rows: list[dict[str, Any]], out_dir: Path) -> list[str]:
        from mpsim.plotting import save_figure, subplots

        fig, ax = subplots(figsize=(5, 3.6))
        for b in self.batches:
            sub = [r for r in rows if r["B"] == b]
            ax.loglog([r["N"] for r in sub], [r["fwd_bwd_s"] for r in sub], "o-", label=f"B={b}")
        ax.set(xlabel="nodes N", ylabel="forward+backward time (s)", title=f"MP-NODE rollout, {self.graph} graph")
        ax.legend()
        return [str(save_figure(fig, Path(out_dir) / "mpnode_scaling.png"))]
