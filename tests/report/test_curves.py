"""`layout=curves` (`mpsim.report.curves`): Figure 5's learning curves of finetuned vs scratch runs."""

import pandas as pd
import pytest

from tests.report.fake_runs import report_of
from tests.report.fake_runs import table2_runs as make_table2_runs


@pytest.fixture
def table2_runs(tmp_path):
    return make_table2_runs(tmp_path / "runs")


def test_curves_overlay_finetune_and_scratch(tmp_path, table2_runs):
    _, out = report_of(tmp_path, "curves", table2_runs)
    text = (out / "report.md").read_text()
    assert "**lorenz10, ds=50** — target: 0.65" in text  # scratch's mean minimum (0.6 and 0.7)
    assert "| MP-NODE finetuned | 1 | 1 | 0.4 @ 2 |" in text  # reaches 0.65 at epoch 1 (0.5)
    assert "| MP-NODE scratch | 2 | 4 | 0.65 @ 4 |" in text
    curves = pd.read_csv(out / "report.csv")
    assert {"system", "n_train", "row", "epoch", "test_error_mean"} <= set(curves.columns)
    assert (out / "curves.png").stat().st_size > 0
