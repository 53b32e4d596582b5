"""`mpsim report` names the runs it leaves out: a run that began training but wrote no summary.json (interrupted,
or still training) is listed with the epoch it reached, in the generic table and in every layout."""

import json
import re

import pandas as pd
import pytest
import yaml

from mpsim.commands.report import run_report
from mpsim.errors import ConfigError, DataError
from mpsim.report import DEFAULT_TITLES
from tests.report.fake_runs import table2_runs as make_table2_runs


def _finished(run, seed):
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump([f"seed={seed}", "data.n_train=50"]))
    pd.DataFrame({"epoch": [0, 1, 2], "val_error": [1.0, 0.5, 0.4], "test_error": [1.0, 0.5, 0.4]}).to_csv(
        run / "metrics.csv", index=False
    )
    summary = {
        "task": "train",
        "mode": "scratch",
        "status": "complete",
        "system": {"name": "lorenz10", "n_nodes": 10},
        "model": {"model": "MPNODE", "config": {"_target_": "mpsim.models.MPNODE", "message_size": 3}},
        "data": {"train": 50, "val": 20, "test": 20, "n_times": 51},
        "min_test_error": 0.4,
        "min_test_error_epoch": 2,
        "epochs_x_min_error": 0.8,
        "initial_test_error": 1.0,
        "epochs_run": 2,
        "test": {"rmse": 0.4},
    }
    (run / "summary.json").write_text(json.dumps(summary))


def _interrupted(run, last_epoch, max_epochs):
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "config.yaml").write_text(yaml.safe_dump({"trainer": {"max_epochs": max_epochs}}))
    (run / "checkpoints").mkdir()
    (run / "checkpoints" / "last.ckpt").write_bytes(b"")
    if last_epoch is not None:
        epochs = list(range(last_epoch + 1))
        pd.DataFrame({"epoch": epochs, "test_error": [1.0] * len(epochs)}).to_csv(run / "metrics.csv", index=False)


@pytest.fixture
def runs(tmp_path):
    root = tmp_path / "runs"
    _finished(root / "s0", 0)
    _finished(root / "s1", 1)
    _interrupted(root / "s2", last_epoch=195, max_epochs=4000)
    _interrupted(root / "s3", last_epoch=None, max_epochs=4000)  # killed before its first epoch was logged
    fix = root / "diagnosis" / "fix" / "added_effect"  # `mpsim diagnose fix=true` trains here: not a run of its own
    (fix / "checkpoints").mkdir(parents=True)
    (fix / "checkpoints" / "last.ckpt").write_bytes(b"")
    pd.DataFrame({"epoch": [0, 1], "test_error": [1.0, 0.5]}).to_csv(fix / "metrics.csv", index=False)
    return root


def test_generic_report_names_the_unfinished_runs_it_leaves_out(cfg_factory, tmp_path, runs):
    result = run_report(cfg_factory("report", f"runs=[{runs}]"), output_dir=tmp_path / "out")
    assert result["n_runs"] == 2
    assert [(r["run"], r["epoch"], r["max_epochs"]) for r in result["unfinished"]] == [
        (str(runs / "s2"), 195, 4000),
        (str(runs / "s3"), None, 4000),
    ]
    text = (tmp_path / "out" / "report.md").read_text()
    assert "Not in the table: 2 runs without summary.json" in text
    assert f"{runs / 's2'} (epoch 195 of 4000)" in text and f"{runs / 's3'} (no epoch logged)" in text


def test_a_layout_report_names_them_too(cfg_factory, tmp_path, runs):
    result = run_report(cfg_factory("report", "layout=curves", f"runs=[{runs}]"), output_dir=tmp_path / "out")
    assert len(result["unfinished"]) == 2
    assert "Not in the table: 2 runs" in (tmp_path / "out" / "report.md").read_text()


def test_a_report_of_finished_runs_says_nothing_about_unfinished_ones(cfg_factory, tmp_path, runs):
    result = run_report(cfg_factory("report", f"runs=[{runs / 's0'},{runs / 's1'}]"), output_dir=tmp_path / "out")
    assert result["unfinished"] == []
    assert "Not in the table" not in (tmp_path / "out" / "report.md").read_text()


def test_only_unfinished_runs_is_one_clear_error(cfg_factory, tmp_path, runs):
    with pytest.raises(ConfigError, match=r"no run there has finished \(1 began training but wrote no summary.json\)"):
        run_report(cfg_factory("report", f"runs=[{runs / 's2'}]"), output_dir=tmp_path / "out")


def test_an_unfinished_run_is_named_with_the_time_it_has_left_at_its_recent_pace(cfg_factory, tmp_path, runs):
    # 300 epochs logged: 1 s each for the first 200, then 3 s each (e.g. a second job took the other core); 4000
    # epochs set. The estimate uses the last 100 epochs' pace: 3700 epochs left × 3 s = 3.1 h
    slow = runs / "s4"
    _interrupted(slow, last_epoch=None, max_epochs=4000)
    wall = [float(e) if e <= 200 else 200.0 + 3.0 * (e - 200) for e in range(301)]
    pd.DataFrame({"epoch": range(301), "test_error": [1.0] * 301, "wall_time": wall}).to_csv(
        slow / "metrics.csv", index=False
    )
    result = run_report(cfg_factory("report", f"runs=[{runs}]"), output_dir=tmp_path / "out")
    (entry,) = [r for r in result["unfinished"] if r["run"] == str(slow)]
    assert entry["epoch"] == 300 and entry["s_per_epoch"] == pytest.approx(3.0)
    text = (tmp_path / "out" / "report.md").read_text()
    assert f"{slow} (epoch 300 of 4000, about 3.1 h left at its last epochs' pace)" in text
    assert f"{runs / 's2'} (epoch 195 of 4000)" in text  # no wall_time column: no estimate, and no guess


def test_runs_that_differ_only_in_where_they_wrote_are_one_row(cfg_factory, tmp_path):
    # seed 0 trained in one folder and seed 1 in a copy of it (a resumed recipe): the same experiment, one row
    root = tmp_path / "runs"
    for seed, where in [(0, "/old/place"), (1, "/new/place")]:
        _finished(root / f"s{seed}", seed)
        saved = root / f"s{seed}" / ".hydra" / "overrides.yaml"
        saved.write_text(yaml.safe_dump([*yaml.safe_load(saved.read_text()), f"paths.output_root={where}"]))
    table = run_report(cfg_factory("report", f"runs=[{root}]"), output_dir=tmp_path / "out")["table"]
    assert len(table) == 1 and table["runs"].tolist() == [2]
    assert "paths.output_root" not in table.columns


def test_an_added_override_groups_under_its_key_and_a_bad_overrides_file_is_refused(cfg_factory, tmp_path):
    # `+key=v` (added) and `key=v` are the same setting: one column, the runs grouped by its values
    root = tmp_path / "runs"
    for seed, item in ((0, "+model.hidden=8"), (1, "model.hidden=8"), (2, "++model.hidden=16")):
        _finished(root / f"s{seed}", seed)
        saved = root / f"s{seed}" / ".hydra" / "overrides.yaml"
        saved.write_text(yaml.safe_dump([*yaml.safe_load(saved.read_text()), item]))
    table = run_report(cfg_factory("report", f"runs=[{root}]"), output_dir=tmp_path / "out")["table"]
    assert dict(zip(table["model.hidden"], table["runs"], strict=True)) == {"8": 2, "16": 1}
    (root / "s2" / ".hydra" / "overrides.yaml").write_text("{seed: 2}")  # a mapping, not a list of overrides
    with pytest.raises(DataError, match="overrides.yaml must be a list of key=value overrides; got dict"):
        run_report(cfg_factory("report", f"runs=[{root}]"), output_dir=tmp_path / "again")


@pytest.mark.parametrize(
    "override, match",
    [
        ("target=abc", "target='abc': give a test error > 0"),  # was a ValueError traceback
        ("target=-1", "target=-1: give a test error > 0"),  # was accepted: a target no run can reach
        ("target=0", "target=0: give a test error > 0"),
        ("runs=[]", "runs=[] names no run"),
        ("layout=curves", "target=max_min applies to the plain table; layout=curves sets its own"),
    ],
)
def test_a_target_no_run_can_reach_or_one_a_layout_ignores_is_refused(cfg_factory, tmp_path, runs, override, match):
    target = [] if override.startswith("target=") else ["target=max_min"]
    cfg = cfg_factory("report", f"runs=[{runs}]", *target, override)
    with pytest.raises(ConfigError, match=re.escape(match)):
        run_report(cfg, output_dir=tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_a_positive_target_gives_the_first_epoch_at_or_below_it(cfg_factory, tmp_path, runs):
    out = run_report(cfg_factory("report", f"runs=[{runs}]", "target=0.5"), output_dir=tmp_path / "out")
    frame = pd.read_csv(tmp_path / "out" / "report.csv")
    assert list(frame["epochs_to_target"]) == [1, 1] and out is not None  # test errors 1.0, 0.5, 0.4


def test_a_report_names_folders_under_where_it_was_started_relative_to_it(cfg_factory, tmp_path, runs, monkeypatch):
    """A report committed beside its runs names no machine's folders: paths under the start folder are printed
    relative to it; paths outside it stay whole."""
    monkeypatch.chdir(tmp_path)
    run_report(cfg_factory("report", f"runs=[{runs}]"), output_dir=tmp_path / "out")
    text = (tmp_path / "out" / "report.md").read_text()
    assert "2 runs under runs." in text
    assert "runs/s2 (epoch 195 of 4000); runs/s3 (no epoch logged)" in text
    assert str(tmp_path) not in text
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    run_report(cfg_factory("report", "layout=curves", f"runs=[{runs}]"), output_dir=tmp_path / "out2")
    text = (tmp_path / "out2" / "report.md").read_text()
    assert f"runs under {runs}." in text and f"{runs / 's2'} (epoch 195 of 4000)" in text


@pytest.fixture
def table2_runs(tmp_path):
    return make_table2_runs(tmp_path / "runs")


def test_unknown_layout_is_refused(cfg_factory, tmp_path, table2_runs):
    cfg = cfg_factory("report", "layout=table3", f"runs=[{table2_runs}]")
    with pytest.raises(ConfigError, match="layout='table3' is unknown; choose one of table2, table1"):
        run_report(cfg, output_dir=tmp_path / "report_table3")


def test_generic_report_is_unchanged_without_a_layout(cfg_factory, tmp_path, table2_runs):
    cfg = cfg_factory("report", f"runs=[{table2_runs}]")
    result = run_report(cfg, output_dir=tmp_path / "plain")
    assert "model_class" not in pd.read_csv(tmp_path / "plain" / "report.csv").columns
    assert result["n_runs"] == 15


def test_a_layout_report_has_its_own_title_unless_one_is_given(cfg_factory, tmp_path, table2_runs):
    run_report(cfg_factory("report", "layout=table2", f"runs=[{table2_runs}]"), output_dir=tmp_path / "own")
    assert (tmp_path / "own" / "report.md").read_text().startswith(f"# {DEFAULT_TITLES['table2']}\n\n15 runs under ")
    cfg = cfg_factory("report", "layout=table2", f"runs=[{table2_runs}]", "title='Table 2 (paper-sized)'")
    result = run_report(cfg, output_dir=tmp_path / "given")
    assert (tmp_path / "given" / "report.md").read_text().startswith("# Table 2 (paper-sized)\n\n15 runs under ")
    assert result["n_runs"] == 15 and result["figures"] == [str(tmp_path / "given" / "table2.png")]


def test_numeric_override_columns_sort_as_numbers(cfg_factory, tmp_path):
    # overrides are text ("8", "16"): sorted as text, 16 came before 8 and 100 before 16
    root = tmp_path / "runs"
    for seed, n_train in enumerate(["16", "100", "8", "8", "null"]):
        _finished(root / f"s{seed}", seed)
        saved = root / f"s{seed}" / ".hydra" / "overrides.yaml"
        saved.write_text(yaml.safe_dump([f"seed={seed}", f"data.n_train={n_train}"]))
    table = run_report(cfg_factory("report", f"runs=[{root}]"), output_dir=tmp_path / "out")["table"]
    assert table["data.n_train"].tolist() == ["8", "16", "100", "null"]  # numbers as numbers, then text
    assert table["runs"].tolist() == [2, 1, 1, 1]
    text = (tmp_path / "out" / "report.md").read_text()
    assert text.index("| 8 |") < text.index("| 16 |") < text.index("| 100 |")


def test_the_jobs_table_is_the_report_of_the_sweep_and_writes_nothing(cfg_factory, tmp_path, runs):
    from mpsim.report import jobs_table

    before = sorted(p for p in runs.rglob("*"))
    text = jobs_table(runs, tmp_path)
    run_report(cfg_factory("report", f"runs=[{runs}]"), output_dir=tmp_path / "out")
    assert text == (tmp_path / "out" / "report.md").read_text().replace(str(runs), "runs")
    assert sorted(p for p in runs.rglob("*")) == before
    assert jobs_table(tmp_path / "out", tmp_path) == ""  # no job wrote a summary
