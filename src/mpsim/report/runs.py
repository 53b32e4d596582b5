"""The runs a report reads: every run directory's summary.json (`collect`), its overrides and resolved settings
(`read_overrides`, `run_settings`), the facts a layout sorts it by (`run_facts`), and the runs that began
training but wrote no summary.json (`unfinished`, `unfinished_note`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pandas as pd
import yaml

from mpsim.config import host_only, output_only, read_overrides_file
from mpsim.errors import DataError
from mpsim.safeload import RECORD_BYTES, SUMMARY_BYTES, load_json, load_yaml

METRICS = (
    "mode",
    "status",
    "epochs_run",
    "min_test_error",
    "min_test_error_epoch",
    "epochs_x_min_error",
    "initial_test_error",
    "test_error",
    "wall_time",
)


def collect(roots: list[Path], facts: bool = False) -> pd.DataFrame:
    """One row per run found under `roots`: overrides as columns plus the summary's scalar metrics (and, with
    `facts`, what the built-in layouts sort runs by: model class, message size, training-set size, ...)."""
    runs = sorted(
        {
            p.parent
            for root in roots
            for p in ([root / "summary.json"] if (root / "summary.json").is_file() else root.rglob("summary.json"))
            if not in_backup(p, root)
        }
    )
    return pd.DataFrame([_row(run, facts) for run in runs])


def in_backup(path: Path, root: Path) -> bool:
    """Whether `path` lies in a `backup-<time>/` folder below `root`: the earlier run that `overwrite=true` moved
    aside inside its folder (`mpsim.runfolder`), not a run of its own (name that folder in runs= to report it)."""
    return any(part.startswith("backup-") for part in path.relative_to(root).parts[:-1])


def unfinished(roots: list[Path]) -> list[dict[str, Any]]:
    """Runs under `roots` that began training but wrote no summary.json (interrupted, or still training), each
    with the last epoch in its metrics.csv, the epochs it was set to run (None where a file does not say) and its
    recent pace in seconds per epoch (None where too few epochs are logged), so a report can name what it leaves
    out, and about how long each would take to finish, instead of averaging over fewer runs without a word."""
    dirs = sorted(
        {
            p.parent if p.name == "metrics.csv" else p.parent.parent
            for root in roots
            if root.is_dir()
            for pattern in ("metrics.csv", "checkpoints/last.ckpt")
            for p in root.rglob(pattern)
            if not in_backup(p, root)
        }
    )
    return [
        {"run": str(d), **_progress(d / "metrics.csv"), "max_epochs": _max_epochs(d)}
        for d in dirs
        if (d / ".hydra").is_dir() and not (d / "summary.json").is_file()  # an `mpsim train` run directory (not,
    ]  # e.g., `mpsim diagnose`'s fix/<tag>, which trains inside the diagnosis and writes no summary of its own)


PACE_EPOCHS = 100  # the time left is estimated at the pace of the last this many logged epochs


def _progress(path: Path) -> dict[str, Any]:
    """The last logged epoch, and the seconds per epoch over the last PACE_EPOCHS epochs from the cumulative
    `wall_time` column (it carries on across a resume); None for what the file does not say."""
    try:
        table = pd.read_csv(path)
        epochs = table["epoch"]
    except (OSError, ValueError, KeyError, pd.errors.ParserError):  # no file yet, no epoch column: nothing to say
        return {"epoch": None, "s_per_epoch": None}
    if not len(epochs):
        return {"epoch": None, "s_per_epoch": None}
    pace = None
    if "wall_time" in table and len(table) >= 2:
        tail = table.iloc[-(PACE_EPOCHS + 1) :]
        try:
            span = float(tail["epoch"].iloc[-1] - tail["epoch"].iloc[0])
            seconds = float(tail["wall_time"].iloc[-1] - tail["wall_time"].iloc[0])
        except (TypeError, ValueError):
            span = seconds = 0.0
        pace = seconds / span if span > 0 and seconds > 0 else None
    try:
        last = int(epochs.iloc[-1])
    except (TypeError, ValueError):
        return {"epoch": None, "s_per_epoch": None}
    return {"epoch": last, "s_per_epoch": pace}


def _max_epochs(run: Path) -> int | None:
    path = run / ".hydra" / "config.yaml"
    try:
        config = load_yaml(path, RECORD_BYTES, str(path), "Restore it")
        value = config["trainer"]["max_epochs"]
    except (OSError, UnicodeDecodeError, yaml.YAMLError, DataError, KeyError, TypeError):
        return None
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def shown(path: str | Path, start_dir: Path | None) -> str:
    """`path` as a report prints it: relative to `start_dir` when it lies under it (so a committed report names
    no machine's folders), else as given."""
    if start_dir is not None:
        try:
            return str(Path(path).relative_to(start_dir))
        except ValueError:
            pass
    return str(path)


def unfinished_note(runs: list[dict[str, Any]], start_dir: Path | None = None) -> str:
    """One paragraph naming the unfinished runs a report leaves out ("" when there are none), their folders
    relative to `start_dir` where they lie under it."""
    if not runs:
        return ""

    def where(r: dict[str, Any]) -> str:
        if r["epoch"] is None:
            return "no epoch logged"
        text = f"epoch {r['epoch']}"
        if r["max_epochs"] is not None:
            text += f" of {r['max_epochs']}"
            left = r["max_epochs"] - r["epoch"]
            if r.get("s_per_epoch") is not None and left > 0:
                text += f", about {_duration(left * r['s_per_epoch'])} left at its last epochs' pace"
        return text

    items = "; ".join(f"{shown(r['run'], start_dir)} ({where(r)})" for r in runs)
    return (
        f"Not in the table: {len(runs)} run{'s' * (len(runs) != 1)} without summary.json (interrupted or still "
        f"training; resume one with `mpsim train resume=<run dir>`): {items}.\n\n"
    )


def read_summary(path: Path) -> dict[str, Any]:
    """A run's summary.json, or a `DataError` naming the file when it is not a JSON object or is larger or more
    deeply nested than mpsim reads (`mpsim.safeload.SUMMARY_BYTES`, `MAX_DEPTH`)."""
    fix = "Rerun that run, or move its directory out of the report's runs"
    try:
        summary = load_json(path, SUMMARY_BYTES, str(path), fix)
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise DataError(
            f"{path} is not valid JSON ({err}). The run did not finish writing it or it was edited: "
            "rerun that run, or move its directory out of the report's runs."
        ) from None
    if not isinstance(summary, dict):
        raise DataError(
            f"{path} must hold a JSON object (a run summary); got a JSON {type(summary).__name__}. "
            "Rerun that run, or move its directory out of the report's runs."
        )
    return summary


def _row(run: Path, facts: bool = False) -> dict[str, Any]:
    summary = read_summary(run / "summary.json")
    row: dict[str, Any] = {"run": str(run)}
    row |= read_overrides(run)
    system = summary.get("system")
    row["system"] = system.get("name") if isinstance(system, dict) else system
    row["task"] = summary.get("task")
    for key in METRICS:
        if key in summary:
            row[key] = summary[key]
    if "test_error" not in row and isinstance(summary.get("test"), dict):
        row["test_error"] = summary["test"].get("rmse")
    if isinstance(summary.get("test"), dict):
        row["test_error"] = summary["test"].get("rmse", row.get("test_error"))
    row |= free_run_columns(summary.get("freerun"))
    if facts:
        row.update(run_facts(run, summary))
        row["settings"] = run_settings(run, summary)
    return row


def free_run_columns(freerun: Any) -> dict[str, Any]:
    """A run's free run of its test records (measured data), as report columns: per record and channel its RMSE
    (raw units) and fit %, `freerun_<file stem>_<channel>_rmse` / `_fit`; none for a run without one."""
    out: dict[str, Any] = {}
    if not isinstance(freerun, dict) or not isinstance(freerun.get("records"), list):
        return out
    for rec in freerun["records"]:
        if not isinstance(rec, dict) or not isinstance(rec.get("channels"), dict):
            continue
        stem = Path(str(rec.get("record", "record"))).stem
        for channel, v in rec["channels"].items():
            if isinstance(v, dict):
                out[f"freerun_{stem}_{channel}_rmse"] = v.get("rmse")
                out[f"freerun_{stem}_{channel}_fit"] = v.get("fit")
    return out


# ---- what a run is and what it ran with --------------------------------------------------------------------
def run_facts(run: Path, summary: dict[str, Any]) -> dict[str, Any]:
    """The facts a layout sorts a run by, read from its summary.json."""
    model, data, test = _section(summary, "model"), _section(summary, "data"), _section(summary, "test")
    config = _section(model, "config")
    return {
        "model_class": model.get("model"),
        "message_size": config.get("message_size"),
        "zero_messages": config.get("zero_messages"),
        "n_train": data.get("train"),
        "n_times": data.get("n_times"),
        "best_val_error": summary.get("best_val_error"),
        "test_rmse": test.get("rmse", summary.get("test_error")),
        "test_rmse_raw": test.get("rmse_raw"),
        "n_features": len(names) if isinstance(names := _section(summary, "system").get("state_names"), list) else None,
        "trained_on": summary.get("trained_on"),
        "init_": summary.get("init"),  # the checkpoint a zero-shot (or finetuned) run started from
        "made_": [str(p) for p in (summary.get("exported"), summary.get("checkpoint")) if isinstance(p, str)],
        "seed_": summary.get("seed"),
        "device": summary.get("device"),  # "cpu (N threads)" / "cuda:0 (name)"; runs from before it was kept: None
        **_step_errors(test.get("per_step_rmse")),
    }


#: rollout steps at which `run_facts` keeps the test RMSE (`test_rmse_step<k>`), where the trajectories are that long
STEPS = (1, 2, 5, 10, 20, 30, 40, 50, 100, 200, 500, 1000)


def _step_errors(per_step: Any) -> dict[str, float]:
    """{"test_rmse_step<k>": RMSE after k rollout steps} from a summary's ``per_step_rmse`` (index = step)."""
    if not isinstance(per_step, list):
        return {}
    out = {}
    for k in STEPS:
        value = per_step[k] if k < len(per_step) else None
        if isinstance(value, int | float) and not isinstance(value, bool):
            out[f"test_rmse_step{k}"] = float(value)
    return out


def _section(parent: dict[str, Any], key: str) -> dict[str, Any]:
    """`parent[key]` if it is a JSON object, else an empty one."""
    value = parent.get(key)
    return value if isinstance(value, dict) else {}


#: resolved-config keys that do not change what a run computes, besides `output_only` and `host_only` ones (and
#: any key named like a seed): what it is, where it started from, what it writes and how it shows progress
INCIDENTAL = {
    "task", "init", "resume", "export", "objective", "memory_check", "mode.name", "system.name", "data.cache",
    "trainer.eval_batch_size",
}  # fmt: skip
INCIDENTAL_PREFIXES = ("eval.", "logger.", "hydra.")


def _incidental(key: str) -> bool:
    last = key.rsplit(".", 1)[-1]
    return (
        "seed" in last or output_only(key) or host_only(key) or key in INCIDENTAL or key.startswith(INCIDENTAL_PREFIXES)
    )


def _flat(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out |= _flat(value, f"{prefix}{key}.")
        else:
            out[f"{prefix}{key}"] = value
    return out


def _text(value: Any) -> str:
    """A setting's value as an override would write it (true, 0.001, [0.0, 50.0], mean)."""
    return (
        value
        if isinstance(value, str)
        else yaml.safe_dump(value, default_flow_style=True).strip().removesuffix("\n...")
    )


def read_overrides(run: Path) -> dict[str, str]:
    """A run's `.hydra/overrides.yaml` as key → value ("+"/"~" prefixes dropped); {} where it kept none. A file
    that is not a YAML list of overrides is a DataError."""
    out = {}
    for item in read_overrides_file(run) or []:
        key, _, value = item.partition("=")
        out[key.lstrip("+~")] = value
    return out


def run_settings(run: Path, summary: dict[str, Any]) -> dict[str, str]:
    """What a run computed with, as key → value text: its resolved Hydra config (`.hydra/config.yaml`; its
    overrides where a run kept no config) with the model's config as summary.json records it (for a zero-shot
    run, the checkpoint's model), less the incidental keys, and less the trainer's for a run that trained
    nothing (zero-shot, evaluation). A config.yaml that is not a YAML mapping is a DataError."""
    tree: Any = None
    config_path = run / ".hydra" / "config.yaml"
    if config_path.is_file():
        try:
            fix = "Restore it or move the run out of the report's runs"  # data only: a python tag is an error
            tree = load_yaml(config_path, RECORD_BYTES, str(config_path), fix)
        except (yaml.YAMLError, UnicodeDecodeError) as err:
            raise DataError(
                f"{config_path} is not valid YAML ({str(err).splitlines()[0]}). Restore it (the run's resolved "
                "config, as Hydra wrote it) or move the run out of the report's runs."
            ) from None
        if not isinstance(tree, dict):
            raise DataError(
                f"{config_path} must hold the run's resolved config (a mapping); got {type(tree).__name__}. "
                "Restore it or move the run out of the report's runs."
            )
    flat = _flat(tree) if isinstance(tree, dict) else dict(read_overrides(run))
    flat = {k: v for k, v in flat.items() if not k.startswith("model.") and k != "model"}
    if summary.get("mode") == "zeroshot" or summary.get("task") != "train":  # it trained nothing: how it would have
        flat = {k: v for k, v in flat.items() if not k.startswith(("trainer.", "mode."))}
    model_config = _section(_section(summary, "model"), "config")
    flat |= _flat({k: v for k, v in model_config.items() if k != "_target_"}, "model.")
    return {k: _text(v) for k, v in flat.items() if not _incidental(k)}
