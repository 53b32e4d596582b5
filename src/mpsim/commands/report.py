"""`mpsim report runs='[<dir>, ...]'`: one table of every run's summary.json joined with its overrides.

Each run directory holds `summary.json` and `.hydra/overrides.yaml`; the overrides become columns, so a
sweep's table has one row per job and one column per swept key. Rows that differ only by `seed` are
aggregated as mean ± std.
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

from mpsim.commands.common import locate, resolve_path
from mpsim.commands.console import print_summary
from mpsim.files import atomic_write
from mpsim.training.metrics import first_epoch_below

log = logging.getLogger(__name__)

METRICS = ("mode", "status", "epochs_run", "min_test_error", "min_test_error_epoch", "epochs_x_min_error",
           "initial_test_error", "test_error", "wall_time")
NUMERIC = ("epochs_to_target", "min_test_error", "min_test_error_epoch", "epochs_x_min_error", "initial_test_error", "test_error",
           "epochs_run", "wall_time")


def collect(roots: list[Path]) -> pd.DataFrame:
    """One row per run found under `roots`: overrides as columns plus the summary's scalar metrics."""
    runs = sorted({p.parent for root in roots for p in ([root / "summary.json"] if (root / "summary.json").is_file()
                                                        else root.rglob("summary.json"))})
    return pd.DataFrame([_row(run) for run in runs])


def _row(run: Path) -> dict[str, Any]:
    summary = json.loads((run / "summary.json").read_text())
    row: dict[str, Any] = {"run": str(run)}
    overrides_path = run / ".hydra" / "overrides.yaml"
    if overrides_path.is_file():
        for item in yaml.safe_load(overrides_path.read_text()) or []:
            key, _, value = str(item).partition("=")
            row[key.lstrip("+~")] = value
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
    return row


def add_epochs_to_target(frame: pd.DataFrame, target: str | float) -> float:
    """Add `epochs_to_target`: the first epoch (≥ 1) whose test error is at or below `target`.

    `target` is a number, or "max_min": the largest of the runs' minimum test errors, i.e. the best level
    that every run reached (so each run has an answer and the slowest run's is its min epoch).
    """
    curves = {}
    for run in frame["run"]:
        path = Path(run) / "metrics.csv"
        if path.is_file():
            m = pd.read_csv(path)
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


def aggregate(frame: pd.DataFrame, group_by: list[str]) -> pd.DataFrame:
    """Mean ± std of the numeric metrics over rows that share `group_by`."""
    numeric = [c for c in NUMERIC if c in frame.columns]
    grouped = frame.groupby(group_by, dropna=False)[numeric]
    mean, std = grouped.mean(), grouped.std()
    out = pd.DataFrame({c: [_pm(m, s) for m, s in zip(mean[c], std[c], strict=True)] for c in numeric},
                       index=mean.index)
    out["runs"] = grouped.size()
    return out.reset_index()


def markdown(frame: pd.DataFrame) -> str:
    """A GitHub-flavoured Markdown table (no extra dependency)."""
    cols = list(frame.columns)
    lines = ["| " + " | ".join(map(str, cols)) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    for _, r in frame.iterrows():
        lines.append("| " + " | ".join(_cell(r[c]) for c in cols) + " |")
    return "\n".join(lines)


def _cell(v: Any) -> str:
    if isinstance(v, float):
        return "" if math.isnan(v) else f"{v:.4g}"
    return "" if v is None else str(v)


def _pm(m: float, s: float) -> str:
    if m is None or math.isnan(m):
        return "nan"
    return f"{m:.4g}" if s is None or math.isnan(s) else f"{m:.4g} ± {s:.2g}"


def run_report(cfg: DictConfig, output_dir: str | Path | None = None, overrides: list[str] | None = None) -> dict:
    """Scan `runs` for summaries; write report.csv (every run) and report.md (grouped by what varies)."""
    start_dir, out_dir = locate(output_dir)
    roots = [Path(m) for pattern in cfg.runs for m in sorted(glob.glob(str(resolve_path(pattern, start_dir))))]
    frame = collect(roots)
    if frame.empty:
        print_summary("mpsim report", [("runs", f"no summary.json found under {list(cfg.runs)}")])
        return {"n_runs": 0}
    frame = frame[~frame["run"].str.startswith(str(out_dir))].reset_index(drop=True)
    if cfg.target is not None:
        add_epochs_to_target(frame, cfg.target)
    fixed = {"run", "seed", "target_error", "status", *NUMERIC}
    varying = [c for c in frame.columns if c not in fixed and frame[c].astype(str).nunique() > 1]
    group_by = list(cfg.group_by) or varying
    table = aggregate(frame, group_by) if group_by else frame.drop(columns=["run"])
    if cfg.columns:
        order = [*group_by, *cfg.columns, "runs"]
        table = table[[c for c in order if c in table.columns]]
    atomic_write(out_dir / "report.csv", lambda f: frame.to_csv(f, index=False), mode="w")
    note = f" Target test error {frame['target_error'].iloc[0]:.4g} ({cfg.target})." if cfg.target is not None else ""
    text = f"# {cfg.title}\n\n{len(frame)} runs under {', '.join(map(str, roots))}.{note}\n\n{markdown(table)}\n"
    atomic_write(out_dir / "report.md", lambda f: f.write(text), mode="w")
    print(text)
    return {"n_runs": len(frame), "report": str(out_dir / "report.md"), "table": table}
