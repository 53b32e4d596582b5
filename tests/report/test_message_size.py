"""`layout=message_size` (`mpsim.report.message_size`): Figures 7 and 8, the minimum test error per message size."""

import pandas as pd
import pytest

import mpsim.report.message_size as layout_module
from tests.report.fake_runs import fake_run, report_of


def test_message_size_layout(tmp_path):
    root = tmp_path / "runs"
    for m, err in ((1, 0.9), (3, 0.5), (7, 0.3), (13, 0.29)):
        for seed in (0, 1):
            fake_run(
                root,
                f"k{m}_{seed}",
                system="kuramoto10_ba",
                seed=seed,
                message_size=m,
                errors=[2.0, 1.0, err + 0.01 * seed],
            )
    fake_run(root, "l2s", system="kuramoto10_ba", model="L2S", message_size=None, errors=[2.0, 1.0, 0.6])
    fake_run(
        root, "zs", system="kuramoto10_ba", message_size=7, trained_on="kuramoto10_er", best_val=0.1
    )  # not trained
    _, out = report_of(tmp_path, "message_size", root)
    text = (out / "report.md").read_text()
    assert "| 7 | 2 | 0.305 ± 0.0071 |" in text
    assert "| L2S | 1 | 0.6 | 6 | 1.2 |" in text  # L2S's final train loss and epochs_x_min_error too (epoch 2 × 0.6)
    table = pd.read_csv(out / "report.csv")
    assert list(table.dropna(subset=["message_size"])["message_size"].astype(int)) == [1, 3, 7, 13]
    assert (out / "message_size.png").is_file() and (out / "message_size_curves.png").is_file()


def test_message_size_layout_compares_runs_at_matched_epochs(tmp_path):
    root = tmp_path / "runs"
    # 8 epochs: m = 1 leads until epoch 4, m = 7 from epoch 6 on; m = 13 stopped after epoch 4
    fake_run(root, "m1", system="kuramoto10_ba", message_size=1, errors=[2, 0.5, 0.4, 0.4, 0.4, 0.4, 0.4, 0.4, 0.4])
    for seed, late in ((0, 0.2), (1, 0.3)):
        errors = [2, 0.9, 0.8, 0.7, 0.6, 0.5, late, 0.9, 0.9]  # a rise after the minimum keeps the minimum so far
        fake_run(root, f"m7_{seed}", system="kuramoto10_ba", seed=seed, message_size=7, errors=errors)
    fake_run(root, "m13", system="kuramoto10_ba", message_size=13, errors=[2, 0.6, 0.5, 0.45, 0.3])
    l2s = [2, 0.7, 0.7, 0.7, 0.7, 0.7, 0.7, 0.7, 0.65, 0.1, 0.1, 0.1, 0.1]  # longer than MP-NODE (as 10000 vs 4000)
    fake_run(root, "l2s", system="kuramoto10_ba", model="L2S", message_size=None, errors=l2s)
    _, out = report_of(tmp_path, "message_size", root)
    text = (out / "report.md").read_text()
    assert "| message size | by epoch 2 | by epoch 4 | by epoch 6 | by epoch 8 |" in text
    assert "| 1 | 0.4 | 0.4 | 0.4 | 0.4 |" in text
    assert "| 7 | 0.8 ± 0 | 0.6 ± 0 | 0.25 ± 0.071 | 0.25 ± 0.071 |" in text
    assert "| 13 | 0.5 | 0.3 | – | – |" in text
    assert "| L2S | 0.7 | 0.7 | 0.7 | 0.65 |" in text  # at MP-NODE's epochs, not the quarters of its own 12


@pytest.fixture
def saved_figures(monkeypatch):
    """The figures a layout saves, by file name, kept open instead of written."""
    saved = {}

    def keep(fig, path):
        saved[path.name] = fig
        return path

    monkeypatch.setattr(layout_module, "save_figure", keep)
    return saved


def test_message_size_figure_does_not_magnify_a_few_percent(tmp_path, saved_figures):
    # Figure 7's three message sizes ended 4 % apart; the report's panel must show them on at least a factor 4
    root = tmp_path / "runs"
    for m, err in ((7, 0.148), (13, 0.142), (20, 0.146)):
        fake_run(root, f"m{m}", system="quad3", message_size=m, errors=[1.0, 0.5, err])
    report_of(tmp_path, "message_size", root)
    fig = saved_figures["message_size.png"]
    lo, hi = fig.axes[0].get_ylim()
    assert hi / lo == pytest.approx(4.0) and lo < 0.142 and 0.148 < hi


def test_message_size_curves_name_l2s_in_both_panels(tmp_path, saved_figures):
    # the curves figure drew L2S's test error unnamed and left its train loss out
    root = tmp_path / "runs"
    fake_run(root, "m7", system="quad3", message_size=7, errors=[1.0, 0.5, 0.3])
    for seed in (0, 1):
        fake_run(root, f"l2s{seed}", system="quad3", model="L2S", seed=seed, message_size=None, errors=[1.0, 0.4, 0.2])
    report_of(tmp_path, "message_size", root)
    train_ax, test_ax = saved_figures["message_size_curves.png"].axes
    for ax in (train_ax, test_ax):
        dashed = [line for line in ax.get_lines() if line.get_linestyle() == "--"]
        assert len(dashed) == 2  # one per L2S seed
    assert [t.get_text() for t in train_ax.get_legend().get_texts()] == ["m=7", "L2S"]
    assert list(train_ax.get_lines()[-1].get_ydata()) == [10.0, 4.0, 2.0]  # train loss is 10x the error (see _run)
