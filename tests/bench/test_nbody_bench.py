"""N-body bench suites on tiny sizes: rows, fitted exponents, targets named in the summary, the paper table."""

from __future__ import annotations

import json
import math

import pytest

from mpsim.bench.nbody import NBodyBench, build, uniform_state
from mpsim.bench.nbody_table import PAPER, NBodyTable
from mpsim.errors import ConfigError


def test_graph_edge_counts() -> None:
    x, nf, box = uniform_state(64)
    assert build("full", x, nf, box) == 64 * 63
    assert build("knn", x, nf, box, k=15) == 64 * 15
    assert 0 < build("hierarchical", x, nf, box) < 64 * 63


def test_suite_rows_summary_and_plot(tmp_path) -> None:
    suite = NBodyBench(
        graph_sizes=[50, 400],
        forward_sizes=[50, 200],
        full_max=400,
        full_forward_max=200,
        sim_sizes=[20, 40],
        sim_steps=4,
        sim_full_max=20,
        sim_steps_large=2,
        sim_batch=3,
        repeats=1,
        memory=False,
        fit_min=1000,
    )
    rows = suite.run()
    parts = {r["part"] for r in rows}
    assert parts == {"graph", "forward", "simulator"}
    graph = [r for r in rows if r["part"] == "graph"]
    assert len(graph) == 6 and all(r["edges_per_particle"] > 0 and r["time_ms"] > 0 for r in graph)
    assert next(r for r in graph if r["kind"] == "knn")["edges_per_particle"] == 15
    fwd = [r for r in rows if r["part"] == "forward"]
    assert len(fwd) == 6 and all(r["step_ms"] >= 0 and math.isnan(r["memory_mb"]) for r in fwd)
    sim = [r for r in rows if r["part"] == "simulator"]
    assert [(r["N"], r["B"], r["steps"]) for r in sim] == [(20, 1, 4), (40, 1, 2), (20, 3, 4)]
    assert all(0 <= r["energy_drift"] < 1e-3 for r in sim)
    text = "\n".join(suite.summarise(rows))
    for phrase in (
        "build time ∝ N^",
        "forward time ∝ N^",
        "expected ≈ 2 (quadratic)",
        "edges per particle vary",
        "per 200-step trajectory",
        "per-trajectory throughput",
    ):
        assert phrase in text, phrase
    (plot,) = suite.plot(rows, tmp_path)
    assert plot.endswith("nbody_scaling.png")


def _summary(run, model: str, graph: str, n: int, system: str) -> None:
    run.mkdir(parents=True)
    summary = {
        "system": {"name": system, "n_nodes": n},
        "model": {
            "model": model,
            "n_params": 1,
            "config": {"_target_": "mpsim.models.deltagn.DeltaGN", "graph": graph, "k": 6},
            "nbody": {
                "graph": graph,
                "energy_error": {"20": 1e-3, "200": 1e-2},
                "data_energy_drift": {"20": 1e-7, "200": 1e-6},
                "n_ill_conditioned": 0,
            },
        },
        "data": {"n_test": 4},
        "test": {"horizons": {"20": {"rmse_raw": 0.03}, "200": {"rmse_raw": 0.4}}, "n_diverged": 1},
        "trained_on": "nbody100",
    }
    (run / "summary.json").write_text(json.dumps(summary))


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_table_reads_runs_and_measures_cost(tmp_path) -> None:
    _summary(tmp_path / "runs" / "a", "DeltaGN", "hierarchical", 100, "nbody100")
    _summary(tmp_path / "runs" / "b", "DeltaGN", "knn", 40, "nbody40")
    (tmp_path / "runs" / "c").mkdir()
    (tmp_path / "runs" / "c" / "summary.json").write_text(json.dumps({"model": {"model": "MPNODE"}}))
    suite = NBodyTable(runs=[str(tmp_path / "runs" / "a"), str(tmp_path / "runs")], measure=False)
    rows = suite.run()
    assert [r["graph"] for r in rows] == ["hierarchical", "knn"]  # in order, deduplicated, non-N-body skipped
    a = rows[0]
    assert (
        a["rmse20"] == 0.03
        and a["energy200"] == 1e-2
        and a["paper_rmse20"] == PAPER[("gravity", "DeltaGN", "hierarchical", 100)][0]
    )
    text = "\n".join(suite.summarise(rows))
    assert "| nbody100 | DeltaGN | hierarchical |" in text and "0.03 / 0.0016" in text and "1/4" in text
    measured = NBodyTable(runs=[str(tmp_path / "runs" / "b")], train_states=1, repeats=1).run()[0]
    assert measured["rollout_step_ms"] > 0 and measured["train_ms_per_state"] > 0
    assert measured["train_peak_mb"] == pytest.approx(measured["train_peak_mb"])  # a number, not NaN


def test_cost_only_rows() -> None:
    (row,) = NBodyTable(cost_only=["deltagn:full:1000"], measure=False).run()
    assert row["trained_on"].startswith("not trained") and math.isnan(row["rmse20"])
    assert row["paper_rmse20"] == pytest.approx(0.2416)
    with pytest.raises(ConfigError, match="deltagn:full:1000"):
        NBodyTable(cost_only=["full:1000"], measure=False).run()


def test_generalisation_rows_get_the_transfer_numbers(tmp_path) -> None:
    """A model evaluated at another N is compared with the paper's cross-N number, not the in-N one."""
    run = tmp_path / "transfer"
    _summary(run, "DeltaGN", "hierarchical", 100, "nbody100")
    summary = json.loads((run / "summary.json").read_text())
    summary["trained_on"] = "nbody1000"
    (run / "summary.json").write_text(json.dumps(summary))
    (row,) = NBodyTable(runs=[str(run)], measure=False).run()
    assert row["trained_on"] == "nbody1000" and row["N"] == 100
    assert row["paper_rmse200"] == pytest.approx(0.117) and math.isnan(row["paper_rmse20"])
    assert "notebook" in row["paper_source"]
