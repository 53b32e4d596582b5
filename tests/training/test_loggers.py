"""Experiment loggers: `mpsim train logger=...` writes what the trainer's epoch hook sends, and it reads back."""

from __future__ import annotations

import csv
import io
import math

import pandas as pd
import pytest

from mpsim.commands.train import run_train
from mpsim.errors import ConfigError
from mpsim.files import atomic_write
from mpsim.training.loggers import CSVLogger, LoggerGroup, flatten, scalars
from tests.helpers import TINY_TRAIN


def test_csv_logger_rewrites_the_history_it_resumes_from(tmp_path):
    log = CSVLogger()
    log.start(tmp_path, {}, [{"epoch": 0, "train_loss": math.nan}, {"epoch": 1, "train_loss": 2.0}])
    log.log_epoch({"epoch": 2, "train_loss": 1.0})
    assert pd.read_csv(tmp_path / "metrics.csv")["epoch"].tolist() == [0, 1, 2]


def test_csv_logger_writes_what_one_full_rewrite_would(tmp_path):
    # each row is formatted once and kept: after a resume and more epochs the file is the whole table, byte for
    # byte what csv.DictWriter writes for every row at once (the format before rows were kept)
    rows = [{"epoch": i, "train_loss": math.nan if i == 0 else 1 / (i + 3), "lr": 1e-3} for i in range(7)]
    log = CSVLogger()
    log.start(tmp_path, {}, rows[:3])
    for row in rows[3:]:
        log.log_epoch(row)
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
    atomic_write(tmp_path / "expected.csv", lambda f: f.write(buf.getvalue()), mode="w")
    assert (tmp_path / "metrics.csv").read_bytes() == (tmp_path / "expected.csv").read_bytes()
    with pytest.raises(ValueError, match="not in fieldnames"):
        log.log_epoch({"epoch": 8, "unknown": 1.0})
    log.start(tmp_path / "again", {}, [])  # a logger started again forgets the earlier run's rows
    (tmp_path / "again").mkdir()
    log.log_epoch({"step": 1})
    assert (tmp_path / "again" / "metrics.csv").read_text().splitlines() == ["step", "1"]


def test_flatten_and_scalars():
    tree = {"a": {"b": 1, "c": [1, 2]}, "d": True, "e": None, "f": math.nan, "g": 2.5}
    assert flatten(tree) == {"a.b": 1, "a.c": [1, 2], "d": True, "e": None, "f": math.nan, "g": 2.5}
    assert scalars(tree) == {"a.b": 1.0, "g": 2.5}


def test_no_logger_writes_no_metrics(cfg_factory, tmp_path):
    run_train(cfg_factory("train", *TINY_TRAIN, "~logger"), output_dir=tmp_path / "run")
    assert not (tmp_path / "run" / "metrics.csv").exists() and (tmp_path / "run" / "summary.json").is_file()


def test_unknown_logger_key_is_refused(cfg_factory, tmp_path):
    with pytest.raises(ConfigError, match="logger.csv.file_name.*Did you mean filename"):
        run_train(cfg_factory("train", *TINY_TRAIN, "+logger.csv.file_name=x.csv"), output_dir=tmp_path / "run")


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_tensorboard_and_mlflow_read_back(cfg_factory, tmp_path):
    pytest.importorskip("tensorboard")
    pytest.importorskip("mlflow")
    from mlflow.tracking import MlflowClient
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from tensorboard.plugins.hparams import plugin_data_pb2

    run_dir = tmp_path / "run"
    summary = run_train(cfg_factory("train", *TINY_TRAIN, "logger=many", "trainer.lr=0.004"), output_dir=run_dir)
    history = pd.read_csv(run_dir / "metrics.csv")  # csv alongside
    epochs = history["epoch"].tolist()
    assert epochs == [0, 1, 2, 3]

    (events,) = (run_dir / "tensorboard").glob("events.out.tfevents.*")
    acc = EventAccumulator(str(events.parent))
    acc.Reload()
    val = acc.Scalars("val_error")
    assert [e.step for e in val] == epochs
    assert [e.value for e in val] == pytest.approx(history["val_error"].tolist(), rel=1e-6)
    assert [e.step for e in acc.Scalars("train_loss")] == epochs[1:]  # epoch 0 has no training loss (NaN)
    assert {"lr", "epoch_time", "grad_norm"} <= set(acc.Tags()["scalars"])
    assert acc.Scalars("summary/best_val_error")[0].value == pytest.approx(summary["best_val_error"], rel=1e-6)
    content = acc.PluginTagToContent("hparams")
    start = plugin_data_pb2.HParamsPluginData.FromString(content["_hparams_/session_start_info"])
    assert start.session_start_info.hparams["trainer.lr"].number_value == pytest.approx(0.004)
    assert start.session_start_info.hparams["model._target_"].string_value == "mpsim.models.mpnode.MPNODE"

    client = MlflowClient(tracking_uri=(tmp_path / "outputs" / "mlruns").as_uri())
    (run,) = client.search_runs([client.get_experiment_by_name("mpsim").experiment_id])
    assert run.info.status == "FINISHED" and run.data.tags["mpsim.run_dir"] == str(run_dir.resolve())
    assert run.data.params["trainer.lr"] == "0.004" and run.data.params["system.name"] == "pendulum2"
    steps = client.get_metric_history(run.info.run_id, "val_error")
    assert [m.step for m in sorted(steps, key=lambda m: m.step)] == epochs
    assert run.data.metrics["summary.best_val_error"] == pytest.approx(summary["best_val_error"], rel=1e-6)
    assert run.data.metrics["summary.test.rmse"] == pytest.approx(summary["test"]["rmse"], rel=1e-6)


def test_logger_group_calls_every_logger_in_order():
    calls = []

    class Probe(CSVLogger):
        def __init__(self, name):
            super().__init__()
            self.name = name

        def start(self, run_dir, hparams=None, history=()):
            calls.append((self.name, "start", dict(hparams)))

        def log_epoch(self, row):
            calls.append((self.name, "epoch", row["epoch"]))

        def finish(self, summary):
            calls.append((self.name, "finish", summary["x"]))

    group = LoggerGroup([Probe("a"), Probe("b")])
    group.start("unused", {"k": 1})
    group.log_epoch({"epoch": 3})
    group.finish({"x": 7})
    assert calls == [
        ("a", "start", {"k": 1}),
        ("b", "start", {"k": 1}),
        ("a", "epoch", 3),
        ("b", "epoch", 3),
        ("a", "finish", 7),
        ("b", "finish", 7),
    ]
