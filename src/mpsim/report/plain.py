"""The plain report (no layout): one row per group of runs that differ only by seed, its metrics as mean ± std
(`plain_table`), and the first epoch each run reached a target test error (`add_epochs_to_target`)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pandas as pd

from mpsim.config import output_only
from mpsim.console import markdown
from mpsim.metrics import first_epoch_below
from mpsim.report.common import read_metrics
from mpsim.report.runs import collect, shown, unfinished, unfinished_note

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


def numeric_columns(frame: pd.DataFrame) -> list[str]:
    """The metrics a report averages: `NUMERIC`, then the free-run scores of measured test records
    (`freerun_<record>_<channel>_rmse` / `_fit`, `mpsim.report.runs.free_run_columns`)."""
    return [c for c in NUMERIC if c in frame.columns] + [c for c in frame.columns if str(c).startswith("freerun_")]


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
    numeric = numeric_columns(frame)
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


def plain_table(frame: pd.DataFrame, group_by: list[str], columns: list[str]) -> pd.DataFrame:
    """The plain report's table of `frame` (one row per run): rows grouped by `group_by` (default: every
    override that varies), metrics as mean ± std, only `columns` of them if given."""
    fixed = {"run", "seed", "target_error", "status", *numeric_columns(frame)}
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


def plain_text(
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
    return plain_text("mpsim report", frame, table, [sweep_dir], start_dir, unfinished([sweep_dir]))
