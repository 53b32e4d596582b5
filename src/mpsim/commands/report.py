"""`mpsim report runs='[<dir>, ...]'`: one table of every run's summary.json joined with its overrides.

Each run directory holds `summary.json` and `.hydra/overrides.yaml`; the overrides become columns, so a
sweep's table has one row per job and one column per swept key. Rows that differ only by `seed` (or by
where they wrote, `paths.*`) are aggregated as mean ± std. Runs that began training but wrote no summary.json (interrupted, or still training)
are not in the table; report.md names each with the epoch it reached.

`layout=table2|table1|curves|message_size|messages` replaces the generic table by one of the MP-NODE paper's tables
or figures (`mpsim.report.layouts`), built from the same runs: report.md (with the settings the runs
used as caption), report.csv (the layout's table, long format), runs.csv (every run) and PNG figures.

This module reads the config and calls the library `mpsim.report`, which does the rest.
"""

from __future__ import annotations

import glob
import logging
import math
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from mpsim.commands.runtime import locate, resolve_path
from mpsim.errors import ConfigError
from mpsim.files import atomic_write
from mpsim.report import (
    LAYOUT_FUNCS,
    add_epochs_to_target,
    collect,
    layout_report,
    plain_table,
    plain_text,
    unfinished,
)

log = logging.getLogger(__name__)

#: the config's default title (conf/report.yaml): a layout then gives its own
DEFAULT_TITLE = "mpsim report"


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
        title = cfg.title if cfg.title != DEFAULT_TITLE else None
        text, result = layout_report(layout, frame, roots, start_dir, out_dir, pending, title)
        print(text)
        return result
    if cfg.target is not None:
        add_epochs_to_target(frame, cfg.target)
    table = plain_table(frame, list(cfg.group_by), list(cfg.columns))
    atomic_write(out_dir / "report.csv", lambda f: frame.to_csv(f, index=False), mode="w")
    note = f" Target test error {frame['target_error'].iloc[0]:.4g} ({cfg.target})." if cfg.target is not None else ""
    text = plain_text(cfg.title, frame, table, roots, start_dir, pending, note)
    atomic_write(out_dir / "report.md", lambda f: f.write(text), mode="w")
    print(text)
    return {"n_runs": len(frame), "report": str(out_dir / "report.md"), "table": table, "unfinished": pending}
