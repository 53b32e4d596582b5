"""`mpsim report runs='[<dir>, ...]'`: one table of every run's summary.json joined with its overrides.

Each run directory holds `summary.json` and `.hydra/overrides.yaml`; the overrides become columns, so a
sweep's table has one row per job and one column per swept key. Rows that differ only by `seed` (or by
where they wrote, `paths.*`) are aggregated as mean ± std. Runs that began training but wrote no summary.json (interrupted, or still training)
are not in the table; report.md names each with the epoch it reached.

`layout=table2|table1|curves|message_size|messages` replaces the generic table by one of the MP-NODE paper's tables
or figures (`mpsim.commands.report_layouts`), built from the same runs: report.md (with the settings the runs
used as caption), report.csv (the layout's table, long format), runs.csv (every run) and PNG figures.
"""

from __future__ import annotations

import glob
import json
import logging
import math
from pathlib import Path
from typing import Any

import pandas as pd
import yaml
from omegaconf import DictConfig

from mpsim.commands.console import markdown
from mpsim.commands.report_layouts import (
    DEFAULT_TITLES,
    LAYOUT_FUNCS,
    mark_variants,
    read_metrics,
    read_overrides,
    run_facts,
    run_settings,
    settings_caption,
)
from mpsim.commands.runtime import locate, resolve_path
from mpsim.config import output_only
from mpsim.errors import ConfigError, DataError
from mpsim.files import atomic_write
from mpsim.metrics import first_epoch_below

log = logging.getLogger(__name__)

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
NUMERIC = (
    "epochs_to_target",
    "min_test_error",
    "min_test_error_epoch",
    "epochs_x_min_error",
    "initial_test_error",
    "test_error",
    "epochs_run",
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
        }
    )
    return pd.DataFrame([_row(run, facts) for run in runs])


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
    try:
        config = yaml.safe_load((run / ".hydra" / "config.yaml").read_text())
        value = config["trainer"]["max_epochs"]
    except (OSError, yaml.YAMLError, KeyError, TypeError):
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
    """A run's summary.json, or a `DataError` naming the file when it is not a JSON object."""
    try:
        summary = json.loads(path.read_text())
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
    if facts:
        row.update(run_facts(run, summary))
        row["settings"] = run_settings(run, summary)
    return row


def add_epochs_to_target(frame: pd.DataFrame, target: str | float) -> float:
    """Add `epochs_to_target`: the first epoch (≥ 1) whose test error is at or below `target`.

    `target` is a number, or "max_min": the largest of the runs' minimum test errors, i.e. the best level
    that every run reached (so each run has an answer and the slowest run's is its min epoch).
    """
    curves = {}
    for run in frame["run"]:
        m = read_metrics(run)
        if m is not None:
            curves[run] = m[m["epoch"] >= 1]
    if target == "max_min":
        value = max(float(c["test_error"].min()) for c in curves.values()) if curves else math.nan
    else:
        value = float(target)
    frame["target_error"] = value
    frame["epochs_to_target"] = [
        first_epoch_below(curves[r]["epoch"].tolist(), curves[r]["test_error"].tolist(), value) if r in curves else None
        for r in frame["run"]
    ]
    return value


def _sort_key(value: Any) -> tuple[int, float, str]:
    """Numbers first, as numbers (8 before 16: an override's value is text, "8" and "16"), then text, then no value."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return (2, 0.0, "")
    try:
        number = float(value) if not isinstance(value, bool) else math.nan
    except (TypeError, ValueError):
        number = math.nan
    return (0, number, "") if not math.isnan(number) else (1, 0.0, str(value))


def aggregate(frame: pd.DataFrame, group_by: list[str]) -> pd.DataFrame:
    """Mean ± std of the numeric metrics over rows that share `group_by`, groups in the order of their values
    (numbers as numbers)."""
    numeric = [c for c in NUMERIC if c in frame.columns]
    rows = sorted(range(len(frame)), key=lambda i: [_sort_key(frame[c].iloc[i]) for c in group_by])
    grouped = frame.iloc[rows].groupby(group_by, dropna=False, sort=False)[numeric]
    mean, std = grouped.mean(), grouped.std()
    out = pd.DataFrame(
        {c: [_pm(m, s) for m, s in zip(mean[c], std[c], strict=True)] for c in numeric}, index=mean.index
    )
    out["runs"] = grouped.size()
    return out.reset_index()


def _pm(m: float, s: float) -> str:
    if m is None or math.isnan(m):
        return "nan"
    return f"{m:.4g}" if s is None or math.isnan(s) else f"{m:.4g} ± {s:.2g}"


def _check_target(target: Any, layout: str | None) -> None:
    """`target` is null, max_min or a test error > 0 (a number, or text that reads as one), and only for the plain
    table (a layout sets its own)."""
    if target is None:
        return
    if layout is not None:
        raise ConfigError(
            f"target={target} applies to the plain table; layout={layout} sets its own (the best level every "
            "curve reaches). Drop target= or layout=."
        )
    if target == "max_min":
        return
    try:
        value = float(target) if not isinstance(target, bool) else math.nan
    except (TypeError, ValueError):
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise ConfigError(
            f"target={target!r}: give a test error > 0 (e.g. target=0.05), or target=max_min (the best level every "
            "run reached)."
        )


def run_report(cfg: DictConfig, output_dir: str | Path | None = None, overrides: list[str] | None = None) -> dict:
    """Scan `runs` for summaries; write report.csv (every run) and report.md (grouped by what varies)."""
    layout = cfg.get("layout")
    if layout is not None and layout not in LAYOUT_FUNCS:
        raise ConfigError(f"layout={layout!r} is unknown; choose one of {', '.join(LAYOUT_FUNCS)} (or null).")
    _check_target(cfg.target, layout)
    if not cfg.runs:
        raise ConfigError("runs=[] names no run; give run or sweep folders, e.g. runs=[outputs/train].")
    start_dir, out_dir = locate(output_dir)
    matches = {str(p): sorted(glob.glob(str(resolve_path(p, start_dir)))) for p in cfg.runs}
    missing = [p for p, found in matches.items() if not found]
    if missing:  # a mistyped path would otherwise drop its runs from the table without a word
        raise ConfigError(
            f"runs: {', '.join(map(repr, missing))} matches no file or folder (relative paths are read from "
            f"{start_dir}); fix the path or leave it out of runs=[...]."
        )
    roots = [Path(m) for found in matches.values() for m in found]
    frame = collect(roots, facts=layout is not None)
    pending = unfinished(roots)
    if frame.empty:
        started = f" ({len(pending)} began training but wrote no summary.json)" if pending else ""
        raise ConfigError(
            f"runs: no summary.json under {', '.join(map(str, roots))}: no run there has finished{started} (a run "
            "writes summary.json when it ends); point runs=[...] at finished run or sweep folders."
        )
    frame = frame[~frame["run"].str.startswith(str(out_dir))].reset_index(drop=True)
    if layout is not None:
        return _run_layout(cfg, layout, frame, roots, start_dir, out_dir, pending)
    if cfg.target is not None:
        add_epochs_to_target(frame, cfg.target)
    table = plain_table(frame, list(cfg.group_by), list(cfg.columns))
    atomic_write(out_dir / "report.csv", lambda f: frame.to_csv(f, index=False), mode="w")
    note = f" Target test error {frame['target_error'].iloc[0]:.4g} ({cfg.target})." if cfg.target is not None else ""
    text = _plain_text(cfg.title, frame, table, roots, start_dir, pending, note)
    atomic_write(out_dir / "report.md", lambda f: f.write(text), mode="w")
    print(text)
    return {"n_runs": len(frame), "report": str(out_dir / "report.md"), "table": table, "unfinished": pending}


def plain_table(frame: pd.DataFrame, group_by: list[str], columns: list[str]) -> pd.DataFrame:
    """The plain report's table of `frame` (one row per run): rows grouped by `group_by` (default: every
    override that varies), metrics as mean ± std, only `columns` of them if given."""
    fixed = {"run", "seed", "target_error", "status", *NUMERIC}
    varying = [c for c in frame.columns if c not in fixed and not output_only(c) and frame[c].astype(str).nunique() > 1]
    group_by = group_by or varying
    if group_by:
        table = aggregate(frame, group_by)
    elif len(frame) > 1:  # the runs differ only by seed (or where they wrote): one row, mean ± std
        table = aggregate(frame.assign(all_runs=""), ["all_runs"]).drop(columns=["all_runs"])
    else:
        table = frame.drop(columns=["run"])
    if columns:
        order = [*group_by, *columns, "runs"]
        table = table[[c for c in order if c in table.columns]]
    return table


def _plain_text(
    title: str,
    frame: pd.DataFrame,
    table: pd.DataFrame,
    roots: list[Path],
    start_dir: Path | None,
    pending: list[dict[str, Any]],
    note: str = "",
) -> str:
    """The plain report as Markdown: title, what it covers, the runs it leaves out, the table."""
    return (
        f"# {title}\n\n{len(frame)} runs under {', '.join(shown(r, start_dir) for r in roots)}.{note}\n\n"
        f"{unfinished_note(pending, start_dir)}{markdown(table)}\n"
    )


def jobs_table(sweep_dir: Path, start_dir: Path | None = None) -> str:
    """The report `mpsim report runs='[<sweep_dir>]'` prints, for the end of a multirun (nothing is written);
    "" when no job wrote a summary."""
    frame = collect([sweep_dir])
    if frame.empty:
        return ""
    table = plain_table(frame, [], [])
    return _plain_text("mpsim report", frame, table, [sweep_dir], start_dir, unfinished([sweep_dir]))


def _split_note(split: list[str]) -> str:
    if not split:
        return ""
    return "Runs in the same place with different settings (each its own row, named by what differs):\n\n" + (
        "\n".join(split) + "\n\n"
    )


def _run_layout(
    cfg: DictConfig,
    layout: str,
    frame: pd.DataFrame,
    roots: list[Path],
    start_dir: Path,
    out_dir: Path,
    pending: list[dict[str, Any]],
) -> dict:
    """Write one built-in layout: report.md, report.csv (its table), runs.csv (every run) and its figures."""
    frame, split = mark_variants(frame)  # runs with other settings are kept apart, not averaged as seeds
    result = LAYOUT_FUNCS[layout](frame, out_dir)
    title = cfg.title if cfg.title != "mpsim report" else DEFAULT_TITLES[layout]
    figures = "".join(f"\n\n![{p.stem}]({p.name})" for p in result.figures)
    text = (
        f"# {title}\n\n{len(frame)} runs under {', '.join(shown(r, start_dir) for r in roots)}. Settings of the "
        f"runs:\n\n{settings_caption(frame)}\n\n{_split_note(split)}{unfinished_note(pending, start_dir)}"
        f"{result.markdown}{figures}\n"
    )
    atomic_write(out_dir / "report.md", lambda f: f.write(text), mode="w")
    atomic_write(out_dir / "report.csv", lambda f: result.table.to_csv(f, index=False), mode="w")
    atomic_write(out_dir / "runs.csv", lambda f: frame.to_csv(f, index=False), mode="w")
    print(text)
    return {
        "n_runs": len(frame),
        "report": str(out_dir / "report.md"),
        "table": result.table,
        "figures": [str(p) for p in result.figures],
        "unfinished": pending,
    }
