"""`layout=table2` (`mpsim.report.table2`) on synthetic run directories: rows, columns, cells, the paper's numbers
and the orderings it claims."""

import pandas as pd
import pytest

from tests.report.fake_runs import fake_run, report_of
from tests.report.fake_runs import table2_runs as make_table2_runs


@pytest.fixture
def table2_runs(tmp_path):
    return make_table2_runs(tmp_path / "runs")


def test_table2_rows_columns_cells_and_orderings(tmp_path, table2_runs):
    result, out = report_of(tmp_path, "table2", table2_runs)
    text = (out / "report.md").read_text()
    assert "| model | Lorenz10 ds=50 | Lorenz10 ds=100 | Gene |" in text  # lorenz3 pre-training is left out
    assert "| MP-NODE finetuned | 0.8 ± 0 | 0.8 ± 0 | 0.2 ± 0 |" in text
    assert "| MP-NODE scratch | 2.6 ± 0.28 | 2.6 ± 0.28 | 1 ± 0 |" in text
    assert "| L2S | N/A | N/A | 1.8 ± 0 |" in text
    assert "- Lorenz10 ds=50: finetuned < scratch (0.8 vs 2.6, 3.2×) — holds; seed by seed: in 2 of 2" in text
    assert "MP-NODE finetuned < L2S" in text
    assert "632.7" in text  # the paper's numbers are printed beside ours
    assert "`lorenz10`: 8 runs, 50/100 training trajectories, 50 steps, up to 4 epochs, seeds 0, 1" in text
    table = pd.read_csv(out / "report.csv")
    assert set(table["row"]) == {"MP-NODE finetuned", "MP-NODE scratch", "L2S"} and (table["runs"] == 2).all()
    assert (out / "table2.png").stat().st_size > 0 and (out / "runs.csv").is_file()
    assert result["n_runs"] == 15


def test_table2_says_in_how_many_seeds_an_ordering_holds(tmp_path):
    root = tmp_path / "runs"
    # seed 0: finetuned 1 × 0.1 = 0.1 < scratch 0.4; seed 1: finetuned 0.6 > scratch 0.4; seed 2 ran only finetuned
    for seed, fine in ((0, [1.0, 0.1, 0.2]), (1, [1.0, 0.7, 0.3]), (2, [1.0, 0.1, 0.2])):
        fake_run(root, f"f{seed}", system="kuramoto10_er", mode="finetune", seed=seed, errors=fine)
    for seed in (0, 1):
        fake_run(root, f"s{seed}", system="kuramoto10_er", seed=seed, errors=[2.0, 0.5, 0.2])
    _, out = report_of(tmp_path, "table2", root)
    text = (out / "report.md").read_text()
    # the means say "holds" (0.267 vs 0.4); the seeds that ran both arms split
    assert "finetuned < scratch (0.2667 vs 0.4, 1.5×) — holds; seed by seed: in 1 of 2" in text
