"""Experiment loggers fed by the trainer's epoch hook: CSV (`metrics.csv`), TensorBoard, MLflow.

A logger has three calls: `start(run_dir, hparams, history)` before the first epoch (``history``: the rows
an interrupted run already recorded, when it resumes), `log_epoch(row)` after every epoch (the trainer's
metrics row: losses, errors, learning rate, gradient norm, epoch and wall time), and `finish(summary)` with
the run's final summary. `LoggerGroup` fans the calls out to several loggers. Config: the `logger` group
(`conf/logger/*.yaml`, one `_target_` node per logger); TensorBoard and MLflow are optional packages
(`pip install 'mpsim[loggers]'`).
"""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from mpsim.errors import ConfigError
from mpsim.files import atomic_write


def flatten(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested mappings to one level with dotted keys (``{"trainer": {"lr": 1e-3}}`` → ``{"trainer.lr": 1e-3}``)."""
    out: dict[str, Any] = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(flatten(value, f"{name}."))
        else:
            out[name] = value
    return out


def scalars(tree: Mapping[str, Any]) -> dict[str, float]:
    """The finite numbers (not booleans) of a nested summary, with dotted keys."""
    return {
        k: float(v)
        for k, v in flatten(tree).items()
        if isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
    }


def _param_value(value: Any) -> int | float | str | bool:
    """A hyper-parameter as a logger accepts it: numbers, strings and booleans as they are, anything else as text."""
    return value if isinstance(value, int | float | str | bool) else str(value)


def _optional(module: str, extra: str = "loggers") -> Any:
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise ConfigError(
            f"logger needs the package {module.split('.')[0]!r}: pip install 'mpsim[{extra}]' (or drop it from logger=)."
        ) from None


class Logger:
    """Base class: every call does nothing."""

    def start(self, run_dir: str | Path, hparams: Mapping[str, Any], history: Sequence[Mapping[str, Any]] = ()) -> None:
        """Before the first epoch: the run directory, the flattened config, rows recorded before a resume."""

    def log_epoch(self, row: Mapping[str, Any]) -> None:
        """After each epoch: the trainer's metrics row (``epoch`` is the step)."""

    def finish(self, summary: Mapping[str, Any]) -> None:
        """After the run: its summary (the numbers of summary.json)."""


class CSVLogger(Logger):
    """`metrics.csv` in the run directory: one row per epoch, rewritten atomically after each (what
    `mpsim report` reads). Each row is formatted once and its text kept, so an epoch costs one write of the
    file, not a re-formatting of every row before it (which took 0.06–0.12 s an epoch at 4000–10000 rows).

    Args:
        filename: file name inside the run directory.
    """

    def __init__(self, filename: str = "metrics.csv") -> None:
        self.filename = filename
        self.path: Path | None = None
        self.fields: list[str] | None = None  # the columns: the first row's keys
        self.lines: list[str] = []  # the header and each row, formatted

    def start(self, run_dir, hparams=None, history=()) -> None:
        self.path = Path(run_dir) / self.filename
        self.fields, self.lines = None, []
        for row in history:
            self._add(row)

    def _add(self, row: Mapping[str, Any]) -> None:
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=self.fields or list(row))
        if self.fields is None:
            self.fields = list(row)
            writer.writeheader()
        writer.writerow(row)
        self.lines.append(buf.getvalue())

    def log_epoch(self, row) -> None:
        if self.path is None:
            raise RuntimeError("CSVLogger.log_epoch before start")
        self._add(row)
        text = "".join(self.lines)
        atomic_write(self.path, lambda f: f.write(text), mode="w")


class TensorBoardLogger(Logger):
    """TensorBoard event file: one scalar per metric and epoch, the config as hyper-parameters (HParams tab,
    with the final summary's numbers as its metrics) and as text.

    Args:
        log_dir: event directory; relative paths are inside the run directory.
    """

    def __init__(self, log_dir: str = "tensorboard") -> None:
        self.log_dir = log_dir
        self.writer: Any = None
        self.hparams: dict[str, Any] = {}

    def start(self, run_dir, hparams=None, history=()) -> None:
        tensorboard = _optional("torch.utils.tensorboard")
        path = Path(self.log_dir)
        self.writer = tensorboard.SummaryWriter(log_dir=str(path if path.is_absolute() else Path(run_dir) / path))
        self.hparams = {k: _param_value(v) for k, v in (hparams or {}).items()}
        if self.hparams and not history:
            text = "\n".join(f"    {k}: {v}" for k, v in self.hparams.items())
            self.writer.add_text("config", text, 0)

    def log_epoch(self, row) -> None:
        step = int(row["epoch"])
        for key, value in row.items():
            if key != "epoch" and isinstance(value, int | float) and math.isfinite(value):
                self.writer.add_scalar(key, value, step)
        self.writer.flush()

    def finish(self, summary) -> None:
        from torch.utils.tensorboard.summary import hparams

        metrics = {f"summary/{k}": v for k, v in scalars(summary).items()}
        for key, value in metrics.items():
            self.writer.add_scalar(key, value, 0)
        exp, start, end = hparams(self.hparams, metrics)
        for item in (exp, start, end):
            self.writer.file_writer.add_summary(item)
        self.writer.close()


class MLflowLogger(Logger):
    """An MLflow run: the config as parameters, one metric per epoch, the final summary as metrics, the run
    directory as a tag. A resumed run continues its MLflow run (found by that tag).

    Args:
        tracking_uri: a directory (a local file store, created if missing) or any MLflow tracking URI, e.g.
            ``sqlite:///outputs/mlflow.db`` (the database store MLflow recommends since 3.x); no default here:
            the command line's is `conf/logger/mlflow.yaml`'s ``${paths.output_root}/mlruns``.
        experiment: experiment name (created if missing).
        run_name: MLflow run name (null: the run directory's name).

    MLflow 3 keeps its file store in maintenance mode and refuses it unless ``MLFLOW_ALLOW_FILE_STORE=true``;
    a directory given here is that explicit choice, so the variable is set (when unset) for this process.
    """

    def __init__(self, tracking_uri: str, experiment: str = "mpsim", run_name: str | None = None) -> None:
        self.tracking_uri, self.experiment, self.run_name = tracking_uri, experiment, run_name
        self.client: Any = None
        self.run_id: str | None = None

    def start(self, run_dir, hparams=None, history=()) -> None:
        tracking = _optional("mlflow.tracking")
        entities = _optional("mlflow.entities")
        uri = self.tracking_uri
        if "://" not in uri and not uri.startswith("file:"):
            uri = Path(uri).resolve().as_uri()
        if uri.startswith("file:"):
            os.environ.setdefault("MLFLOW_ALLOW_FILE_STORE", "true")
        self.client = tracking.MlflowClient(tracking_uri=uri)
        found = self.client.get_experiment_by_name(self.experiment)
        exp_id = found.experiment_id if found is not None else self.client.create_experiment(self.experiment)
        run_dir = str(Path(run_dir).resolve())
        earlier = (
            self.client.search_runs([exp_id], filter_string=f"tags.`mpsim.run_dir` = '{run_dir}'") if history else []
        )
        if earlier:
            self.run_id = earlier[0].info.run_id
            self.client.update_run(self.run_id, status="RUNNING")
            return
        run = self.client.create_run(
            exp_id, run_name=self.run_name or Path(run_dir).name, tags={"mpsim.run_dir": run_dir}
        )
        self.run_id = run.info.run_id
        params = [entities.Param(k[:250], str(_param_value(v))[:500]) for k, v in (hparams or {}).items()]
        for chunk in _chunks(params, 100):
            self.client.log_batch(self.run_id, params=chunk)

    def log_epoch(self, row) -> None:
        from mlflow.entities import Metric

        step, stamp = int(row["epoch"]), _now_ms()
        metrics = [
            Metric(k, float(v), stamp, step)
            for k, v in row.items()
            if k != "epoch" and isinstance(v, int | float) and math.isfinite(v)
        ]
        self.client.log_batch(self.run_id, metrics=metrics)

    def finish(self, summary) -> None:
        from mlflow.entities import Metric

        stamp = _now_ms()
        metrics = [Metric(f"summary.{k}"[:250], v, stamp, 0) for k, v in scalars(summary).items()]
        for chunk in _chunks(metrics, 1000):
            self.client.log_batch(self.run_id, metrics=chunk)
        status = str(summary.get("status", ""))
        self.client.set_tag(self.run_id, "mpsim.status", status)
        self.client.set_terminated(self.run_id, status="FAILED" if status == "diverged" else "FINISHED")


def _chunks(items: list[Any], size: int) -> Iterable[list[Any]]:
    for start in range(0, len(items), size):
        yield items[start : start + size]


def _now_ms() -> int:
    import time

    return int(time.time() * 1000)


class LoggerGroup(Logger):
    """Several loggers behind one: each call goes to every logger, in order."""

    def __init__(self, loggers: Iterable[Logger] = ()) -> None:
        self.loggers = list(loggers)

    def start(self, run_dir, hparams=None, history=()) -> None:
        for logger in self.loggers:
            logger.start(run_dir, hparams or {}, history)

    def log_epoch(self, row) -> None:
        for logger in self.loggers:
            logger.log_epoch(row)

    def finish(self, summary) -> None:
        for logger in self.loggers:
            logger.finish(summary)
