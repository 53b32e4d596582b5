"""S-MNN bench suite: rows for every solver, refusal of dense solves over budget, summary and CLI outputs."""

from __future__ import annotations

import math

import pytest

from mpsim.bench.smnn import SMNNBench, lorenz_inputs
from tests.helpers import run_mpsim_ok


def test_inputs_have_the_lorenz_discovery_shapes():
    coef, rhs, init = lorenz_inputs(8, 50, "shared")
    assert coef.shape == (1, 1, 1, 1, 1, 3) and rhs.shape == (8, 3, 50, 1) and init.shape == (8, 3, 1, 1, 1)
    assert not coef.requires_grad and rhs.requires_grad
    coef, _, _ = lorenz_inputs(8, 50, "per_sample")
    assert coef.shape == (8, 3, 1, 1, 1, 3) and coef.requires_grad


def test_rows_summary_and_exponents():
    suite = SMNNBench(
        lengths=[5, 20, 40], batches=[4, 8], base_batch=8, base_length=20, repeats=1, memory=False, fit_from=5
    )
    rows = suite.run()
    assert len(rows) == 2 * 4 * 4  # two LHS modes x (3 lengths + 1 extra batch) x 4 solvers
    assert all(r["status"] == "ok" and r["fwd_bwd_ms"] > 0 for r in rows)
    lines = suite.summarise(rows)
    assert any("banded is" in line and "faster than dense" in line for line in lines)
    # paper Table 1 layout: one column per (batch, T), a time row and a memory row per solver and LHS mode
    assert "| (batch, T) | (8, 5) | (8, 20) | (8, 40) | (4, 20) |" in lines
    row = next(line for line in lines if line.startswith("| time, ms: S-MNN banded (shared LHS) |"))
    assert len(row.split("|")) == 7 and all(float(c) > 0 for c in row.split("|")[2:6])
    assert sum(line.startswith("| peak memory, MiB: ") for line in lines) == 8
    # fitted exponents: time over T and over batch for every solver (memory not measured here)
    fits = [line for line in lines if line.startswith("| MNN dense (slack) (per-sample LHS) |")]
    assert len(fits) == 1 and "(T = 5…40)" in fits[0] and "(batch = 4…8)" in fits[0] and "| — |" in fits[0]


def test_dense_is_refused_over_budget_not_crashed():
    suite = SMNNBench(
        lengths=[30],
        batches=[16],
        base_batch=16,
        base_length=30,
        lhs_modes=["per_sample"],
        dense_budget_gib=1e-4,
        repeats=1,
        memory=False,
    )
    rows = {r["method"]: r for r in suite.run()}
    for method in ("dense", "mnn"):
        assert rows[method]["status"].startswith("refused: needs ") and "GiB" in rows[method]["status"]
        assert math.isnan(rows[method]["fwd_bwd_ms"])
    assert rows["banded"]["status"] == rows["cyclic"]["status"] == "ok"
    assert any("refused" in line for line in suite.summarise(list(rows.values())))


@pytest.mark.slow  # long; outside the default suite (<4 min on 2 cores), run by .ci/run's -m slow step
def test_peak_memory_grows_with_the_dense_matrix():
    suite = SMNNBench(methods=["dense"], lhs_modes=["shared"], repeats=1)
    small = suite._measure("dense", 8, 50, "shared")["peak_mib"]
    large = suite._measure("dense", 8, 800, "shared")["peak_mib"]  # 2400² doubles: ≥ 44 MiB per copy
    assert large - small > 40


def test_bad_method_is_refused():
    with pytest.raises(ValueError, match="bench.methods"):
        SMNNBench(methods=["qr"])


def test_cli_writes_table_and_plot(tmp_path):
    run_mpsim_ok(
        [
            "bench",
            "bench=smnn",
            "bench.lengths=[5,20]",
            "bench.batches=[4]",
            "bench.base_batch=4",
            "bench.base_length=20",
            "bench.repeats=1",
            "bench.memory=false",
            "bench.fit_from=5",
        ],
        tmp_path,
    )
    (run,) = sorted(p.parent for p in (tmp_path / "outputs" / "bench").rglob("bench.md"))
    text = (run / "bench.md").read_text()
    assert "fwd_bwd_ms" in text and "banded" in text and (run / "plots" / "smnn_scaling.png").is_file()


def test_table3_suite_reproduces_the_published_values():
    from mpsim.bench.smnn_table3 import Table3Bench

    suite = Table3Bench(methods=["banded", "cyclic"], repeats=1)
    rows = suite.run()
    assert len(rows) == 6 * 2 * 3  # ODEs x solvers x orders
    assert all(1 / 3 < r["ratio"] < 3 for r in rows), [(r["ode"], r["order"], r["ratio"]) for r in rows]
    lines = suite.summarise(rows)
    assert lines[2] == "| order | R | P | L | H | D | T |"
    assert lines[4].startswith("| u, banded | ") and "(4.8e-12)" in lines[4]
    assert any(line.startswith("- measured / published: ") for line in lines)
