"""Every layout (`mpsim.report.layouts`) over runs it cannot place says what it lacks."""

import json

import pytest

from tests.report.fake_runs import fake_run, report_of


@pytest.mark.parametrize("layout", ["table1", "table2", "curves", "message_size", "messages"])
def test_a_layout_over_zero_shot_runs_only_says_what_it_lacks(tmp_path, layout):
    # the training run has not finished (no summary.json), its zero-shot runs have: no column a training run writes
    root = tmp_path / "runs"
    fake_run(root, "er", system="gene_er_small", trained_on="gene_ba_small", best_val=0.3)
    result, out = report_of(tmp_path, layout, root)
    assert result["n_runs"] == 1
    assert "- `gene_er_small`: 1 run, 50 steps, seed 0\n" in (out / "report.md").read_text()


@pytest.mark.parametrize("layout", ["table1", "table2", "curves", "message_size", "messages"])
def test_a_layout_over_other_tasks_summaries_finds_no_training_run(tmp_path, layout):
    # a bench table and a simulated dataset beside the runs: summaries without a mode, model or training set
    for name, summary in (
        ("bench", {"task": "bench", "suite": "epoch_time", "rows": []}),
        ("sim", {"task": "simulate"}),
    ):
        (tmp_path / "runs" / name).mkdir(parents=True)
        (tmp_path / "runs" / name / "summary.json").write_text(json.dumps(summary))
    result, out = report_of(tmp_path, layout, tmp_path / "runs")
    assert result["n_runs"] == 2 and "training runs found." in (out / "report.md").read_text()
