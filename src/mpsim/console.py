"""Text for people: numbers and durations as the commands print them, the one-screen summary a command prints when
it ends, and the Markdown tables that `report`, `bench` and `diagnose` write."""

from __future__ import annotations

import math
import shutil
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import pandas as pd


def fmt(v: Any, digits: int = 4) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        if not math.isfinite(v):
            return "nan"
        return f"{v:.{digits}g}"
    return str(v)


def duration(seconds: float | None) -> str:
    if seconds is None or not math.isfinite(seconds):
        return "-"
    m, s = divmod(seconds, 60)
    return f"{int(m)}m {s:04.1f}s" if m else f"{s:.1f}s"


def print_summary(title: str, rows: list[tuple[str, str]]) -> None:
    """Print `rows` of (label, value) under a rule with `title`."""
    width = min(shutil.get_terminal_size((100, 20)).columns, 100)
    label_w = max(len(label) for label, _ in rows) + 2
    print("\n" + f" {title} ".center(width, "─"))
    for label, value in rows:
        print(f" {label:<{label_w}}{value}")
    print("─" * width)


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
