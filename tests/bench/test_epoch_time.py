"""`bench=epoch_time`: real training runs, their per-epoch times and the projected paper budget."""

import pytest

from mpsim.bench.epoch_time import PAPER_CASES, EpochTimeBench
from mpsim.errors import ConfigError


def test_epoch_time_rows_come_from_a_real_training_run():
    bench = EpochTimeBench(
        cases=[
            {
                "name": "tiny",
                "overrides": ["system=pendulum2", "data.n_train=8", "data.horizon=10"],
                "paper_epochs": 4000,
            }
        ],
        epochs=3,
    )
    (row,) = bench.run()
    assert row["case"] == "tiny" and row["epochs_timed"] == 2  # epoch 0 (evaluation) and the warm-up dropped
    assert 0 < row["train_pass_s"] <= row["epoch_with_eval_s"]
    assert row["paper_budget_h"] == pytest.approx(4000 * row["epoch_with_eval_s"] / 3600, abs=0.006)
    assert f"{row['paper_budget_h']:.1f} h" in bench.summarise([row])[0]


def test_epoch_time_refuses_bad_cases_and_keeps_paper_defaults():
    with pytest.raises(ConfigError, match="name and a list of overrides"):
        EpochTimeBench(cases=[{"name": "x", "overrides": "system=lorenz3"}])
    with pytest.raises(ConfigError, match="epochs must be >= 2"):
        EpochTimeBench(epochs=1)
    assert {c["paper_epochs"] for c in PAPER_CASES} == {4000, 10000}  # MP-NODE 4000, L2S 10000 (the paper's)


def test_a_failing_case_names_its_command():
    bench = EpochTimeBench(cases=[{"name": "bad", "overrides": ["system=no_such_system"]}], epochs=2)
    with pytest.raises(RuntimeError, match="system=no_such_system"):
        bench.run()
