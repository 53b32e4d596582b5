"""The built-in layouts by name (`LAYOUT_FUNCS`, `DEFAULT_TITLES`) and the report one of them writes
(`layout_report`): report.md with the runs' settings as caption, report.csv (the layout's table, long format),
runs.csv (every run) and the layout's PNG figures."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pandas as pd

from mpsim.files import atomic_write
from mpsim.report.common import LayoutResult
from mpsim.report.curves import curves
from mpsim.report.message_size import message_size
from mpsim.report.messages import messages
from mpsim.report.runs import shown, unfinished_note
from mpsim.report.table1 import table1
from mpsim.report.table2 import table2
from mpsim.report.variants import mark_variants, settings_caption

LAYOUT_FUNCS: dict[str, Callable[[pd.DataFrame, Path], LayoutResult]] = {
    "table2": table2,
    "table1": table1,
    "curves": curves,
    "message_size": message_size,
    "messages": messages,
}
DEFAULT_TITLES = {
    "table2": "Table 2: MP-NODE finetuned vs from scratch vs L2S",
    "table1": "Table 1: zero-shot generalisation of MP-NODE (gene 4×4, trained on BA)",
    "curves": "Figure 5: finetuning vs training from scratch",
    "message_size": "Figures 7 and 8: effect of the message size",
    "messages": "Figures 3a and 4: MP-NODE with messages vs without (`model.zero_messages=true`)",
}


def _split_note(split: list[str]) -> str:
    if not split:
        return ""
    return "Runs in the same place with different settings (each its own row, named by what differs):\n\n" + (
        "\n".join(split) + "\n\n"
    )


def layout_report(
    layout: str,
    frame: pd.DataFrame,
    roots: list[Path],
    start_dir: Path,
    out_dir: Path,
    pending: list[dict[str, Any]],
    title: str | None = None,
) -> tuple[str, dict]:
    """Write one built-in layout of the runs in `frame` (from `collect(roots, facts=True)`; `pending` from
    `unfinished(roots)`): report.md, report.csv (its table), runs.csv (every run) and its figures, all in
    `out_dir`, the folders named relative to `start_dir`. `title` None: the layout's own (`DEFAULT_TITLES`).
    Returns report.md's text and what was written."""
    frame, split = mark_variants(frame)  # runs with other settings are kept apart, not averaged as seeds
    result = LAYOUT_FUNCS[layout](frame, out_dir)
    title = title if title is not None else DEFAULT_TITLES[layout]
    figures = "".join(f"\n\n![{p.stem}]({p.name})" for p in result.figures)
    text = (
        f"# {title}\n\n{len(frame)} runs under {', '.join(shown(r, start_dir) for r in roots)}. Settings of the "
        f"runs:\n\n{settings_caption(frame)}\n\n{_split_note(split)}{unfinished_note(pending, start_dir)}"
        f"{result.markdown}{figures}\n"
    )
    atomic_write(out_dir / "report.md", lambda f: f.write(text), mode="w")
    atomic_write(out_dir / "report.csv", lambda f: result.table.to_csv(f, index=False), mode="w")
    atomic_write(out_dir / "runs.csv", lambda f: frame.to_csv(f, index=False), mode="w")
    return text, {
        "n_runs": len(frame),
        "report": str(out_dir / "report.md"),
        "table": result.table,
        "figures": [str(p) for p in result.figures],
        "unfinished": pending,
    }
