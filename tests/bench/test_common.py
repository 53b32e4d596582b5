import functools
import math

import pytest
import torch

from mpsim.bench.common import peak_memory_mb, scaling_exponent, timeit
from mpsim.bench.mpnode import MPNODEBench
from mpsim.errors import ConfigError


def test_scaling_exponent_recovers_powers():
    n = [10, 100, 1000]
    assert scaling_exponent(n, [3 * v for v in n]) == pytest.approx(1.0)
    assert scaling_exponent(n, [v**2 for v in n]) == pytest.approx(2.0)
    assert math.isnan(scaling_exponent([10], [1.0]))


def _allocate(mb):
    x = torch.ones(int(mb * 2**20 / 8), dtype=torch.float64)
    return float(x.sum())


@pytest.mark.slow  # long; outside the default suite (<4 min on 2 cores), run by .ci/run's -m slow step
def test_peak_memory_sees_an_allocation():
    small = peak_memory_mb(functools.partial(_allocate, 1))
    big = peak_memory_mb(functools.partial(_allocate, 200))
    assert 150 < big - small < 260, (small, big)


def test_timeit_counts_runs():
    calls = []
    out = timeit(lambda: calls.append(1), repeats=3, warmup=2)
    assert out["runs"] == 3 and len(calls) == 5 and out["min_s"] <= out["median_s"]


def test_mpnode_suite_rows_and_summary():
    suite = MPNODEBench(nodes=[2, 4], batches=[1, 4], steps=3, repeats=1)
    rows = suite.run()
    assert len(rows) == 4 and {"N", "B", "fwd_bwd_s"} <= set(rows[0])
    assert any("cheaper per node-trajectory" in line for line in suite.summarise(rows))
    assert all(r["edge_list_fwd_bwd_s"] > 0 and r["dense_speedup"] > 0 for r in rows)
    assert all(r["odeint_fwd_bwd_s"] > 0 and r["stacked_speedup"] > 0 for r in rows)
    summary = suite.summarise(rows)
    assert any("edge-list aggregation / dense adjacency product" in line for line in summary)
    assert any("torchdiffeq's odeint as is / stacked outputs" in line for line in summary)
    assert all(r["torch_tanh_fwd_bwd_s"] > 0 and r["tanh_speedup"] > 0 for r in rows)
    assert any("torch's nn.Tanh / layers.Tanh" in line for line in summary)


def test_the_torch_tanh_copy_swaps_every_tanh_and_keeps_the_weights_and_the_values():
    from torch import nn

    from mpsim.bench.mpnode import with_torch_tanh
    from mpsim.models.layers import Tanh
    from mpsim.models.mpnode import MPNODE

    model = MPNODE(3)
    clone = with_torch_tanh(model)
    assert sum(isinstance(m, Tanh) for m in model.modules()) == 2  # the paper's MLP: two hidden layers
    assert not any(isinstance(m, Tanh) for m in clone.modules())
    assert sum(type(m) is nn.Tanh for m in clone.modules()) == 2
    x = torch.randn(5, 3 + 3)
    assert torch.allclose(model.net(x), clone.net(x), atol=1e-6)
    ours, theirs = model.state_dict(), clone.state_dict()
    assert ours.keys() == theirs.keys() and all(torch.equal(ours[k], theirs[k]) for k in ours)


def test_mpnode_suite_times_the_gene_graphs_and_refuses_an_unknown_graph():
    (row,) = MPNODEBench(nodes=[8], batches=[2], graph="ba", steps=2, repeats=1).run()
    assert row["E"] == 2 * (8 - 4) * 4  # BA(8, 4) as networkx draws it: m(n - m) = 16 edges, both ways
    with pytest.raises(ConfigError, match="bench.graph"):
        MPNODEBench(graph="grid")
