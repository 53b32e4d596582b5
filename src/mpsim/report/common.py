"""What the layouts share: the result they return, the names of models and systems in their rows and columns,
statistics over seeds, Markdown cells and tables, learning curves (`metrics.csv`) and their minima so far."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from mpsim.errors import DataError

FAMILIES = (("lorenz", None), ("kuramoto", "Kuramoto"), ("gene", "Gene"), ("quad", "Quadrotors"))
MODEL_NAMES = {"MPNODE": "MP-NODE", "L2S": "L2S", "NODE": "NODE"}


@dataclass
class LayoutResult:
    """What a layout produced: Markdown body, a long table for the CSV, and the figures it wrote."""

    markdown: str
    table: pd.DataFrame
    figures: list[Path]


# ---- names of rows and columns -----------------------------------------------------------------------------
def model_name(model_class: Any, variant: Any = "") -> str:
    """A model's name in a layout's rows ("MP-NODE", "L2S", ...) with its variant, if any."""
    return MODEL_NAMES.get(str(model_class), str(model_class)) + (variant if isinstance(variant, str) else "")


def row_label(model_class: Any, mode: Any, variant: Any = "") -> str:
    """Table 2 row of a run: "MP-NODE finetuned", "MP-NODE scratch", "L2S", ... (with its variant, if any)."""
    name = MODEL_NAMES.get(str(model_class), str(model_class))
    tail = variant if isinstance(variant, str) else ""
    if name == "MP-NODE":
        return f"MP-NODE {'finetuned' if mode == 'finetune' else 'scratch'}{tail}"
    return (f"{name} finetuned" if mode == "finetune" else name) + tail


def family(system: str) -> str:
    """Column family of a system name: Lorenz10, Kuramoto, Gene, Quadrotors, or the name itself."""
    low = system.lower()
    for prefix, label in FAMILIES:
        if low.startswith(prefix):
            return label or system[:1].upper() + system[1:]
    return system


def graph_family(system: str) -> str:
    """The random-graph family in a system name (gene_er_small → ER), or the name itself."""
    parts = system.lower().split("_")
    for short in ("ba", "er", "ws"):
        if short in parts or any(p.endswith(short) and p[:-2].isdigit() for p in parts):
            return short.upper()
    return system


def target_systems(train: pd.DataFrame) -> list[str]:
    """Systems some run was finetuned on (all systems when none was)."""
    fine = sorted(set(train.loc[train["mode"] == "finetune", "system"]))
    return fine or sorted(set(train["system"]))


def column_key(system: str) -> tuple[int, str]:
    """Sort key of a system's column: the families in the paper's order (Lorenz, Kuramoto, Gene, Quadrotors), then
    any other, each by name."""
    order = {label or "Lorenz": k for k, (_, label) in enumerate(FAMILIES)}
    fam = family(system)
    return (order.get("Lorenz" if fam.lower().startswith("lorenz") else fam, len(order)), system)


def row_order(row: str) -> tuple[int, str]:
    """Finetuned, scratch, L2S (each with its variants, `mark_variants`), then any other model."""
    order = ["MP-NODE finetuned", "MP-NODE scratch", "L2S"]
    base = next((k for k, o in enumerate(order) if row == o or row.startswith(f"{o} (")), len(order))
    return (base, row)


# ---- statistics over seeds and Markdown ---------------------------------------------------------------------
def mean_std_count(values: pd.Series) -> tuple[float, float, int]:
    """(mean, std, count) of the numbers among `values` (NaN for a mean of none or a std of fewer than two)."""
    v = pd.to_numeric(values, errors="coerce").dropna()
    return (float(v.mean()) if len(v) else math.nan, float(v.std()) if len(v) > 1 else math.nan, int(len(v)))


def pm(mean: float, std: float, digits: int = 4) -> str:
    """ "mean ± std" (std omitted for a single value, "N/A" without a value)."""
    if mean is None or (isinstance(mean, float) and math.isnan(mean)):
        return "N/A"
    text = f"{mean:.{digits}g}"
    return text if std is None or math.isnan(std) else f"{text} ± {std:.2g}"


def md_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub-flavoured Markdown table."""
    lines = ["| " + " | ".join(map(str, header)) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(map(str, r)) + " |" for r in rows]
    return "\n".join(lines)


def as_numbers(frame: pd.DataFrame, column: str) -> pd.Series:
    """`frame[column]` as numbers (NaN where not one); all NaN where no run recorded the column."""
    if column not in frame:
        return pd.Series(math.nan, index=frame.index, dtype=float)
    return pd.to_numeric(frame[column], errors="coerce")


def norm_scale(part: pd.DataFrame) -> float:
    """Raw over normalised test RMSE, mean over runs: the state std each run's errors are divided by. Only for
    one-feature systems (gene), where the ratio is that std exactly; NaN otherwise."""
    if "test_rmse_raw" not in part or not (as_numbers(part, "n_features") == 1).all():
        return math.nan
    ratio = pd.to_numeric(part["test_rmse_raw"], errors="coerce") / pd.to_numeric(part["test_rmse"], errors="coerce")
    ratio = ratio[ratio > 0]
    return float(ratio.mean()) if len(ratio) else math.nan


def run_norm_scale(run: dict[str, Any]) -> float:
    """One run's raw over normalised test RMSE (its state std on a one-feature system)."""
    return float(run["test_rmse_raw"]) / float(run["test_rmse"])


def mixed_units(scales: dict[str, float]) -> bool:
    """Whether rows (row → `norm_scale`) were normalised by stds more than 1 % apart; False where one is unknown."""
    values = list(scales.values())
    return len(values) > 1 and all(math.isfinite(v) for v in values) and max(values) > 1.01 * min(values)


# ---- learning curves ---------------------------------------------------------------------------------------
def read_metrics(run: str | Path) -> pd.DataFrame | None:
    """A run's `metrics.csv` (None where it has none, or no rows yet), every column numeric. A file that is not
    such a table (not CSV, no `epoch` or `test_error` column, text where a number belongs) is a DataError naming
    the file, the column and the row."""
    path = Path(run) / "metrics.csv"
    if not path.is_file():
        return None
    try:
        m = pd.read_csv(path)
    except pd.errors.EmptyDataError:
        return None
    except (pd.errors.ParserError, UnicodeDecodeError, ValueError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise DataError(f"{path} cannot be read as CSV ({first}); restore it or move the run out of runs.") from None
    missing = [c for c in ("epoch", "test_error") if c not in m]
    if missing:
        raise DataError(f"{path} has no {' or '.join(missing)} column; it is not a metrics.csv that mpsim train wrote.")
    for column in m.columns:
        values = pd.to_numeric(m[column], errors="coerce")
        bad = values.isna() & m[column].notna()
        if bad.any():
            row = int(bad.to_numpy().nonzero()[0][0])
            raise DataError(
                f"{path}: column {column!r} holds {m[column].iloc[row]!r} in row {row + 2} (not a number); "
                "restore the file or move the run out of runs."
            )
        m[column] = values
    return m if len(m) else None


def mean_band(ax: Any, curves: Sequence[pd.DataFrame], key: str, label: str, color: str | None = None) -> pd.DataFrame:
    """Draw the mean of `key` per epoch over the runs' curves with a min–max band; return the runs side by side."""
    wide = pd.concat([c.set_index("epoch")[key] for c in curves], axis=1)  # [epoch, run]
    mean = wide.mean(axis=1)
    (line,) = ax.plot(mean.index, mean.values, color=color, label=label)
    ax.fill_between(mean.index, wide.min(axis=1), wide.max(axis=1), color=line.get_color(), alpha=0.2)
    return wide


def checkpoint_epochs(curves: Sequence[pd.DataFrame]) -> list[int]:
    """The quarters of the longest run (1000/2000/3000/4000 for 4000 epochs): where runs are compared."""
    last = max((int(c["epoch"].max()) for c in curves), default=0)
    return sorted({max(1, round(last * q / 4)) for q in (1, 2, 3, 4)}) if last >= 1 else []


def min_so_far(curve: pd.DataFrame, epochs: Sequence[int], key: str = "test_error") -> list[float]:
    """The curve's minimum `key` over epochs 1..e for each e (NaN where the run stopped before e)."""
    trained = curve[curve["epoch"] >= 1].set_index("epoch")[key].sort_index().cummin()
    return [float(trained[trained.index <= e].iloc[-1]) if trained.index.max() >= e else math.nan for e in epochs]


def by_epoch_row(
    label: Any, curves: Sequence[pd.DataFrame], epochs: Sequence[int], key: str = "test_error"
) -> list[Any]:
    """A table row: `label`, then the runs' minimum `key` so far at each of `epochs` as mean ± std ("–" where a
    run stopped before that epoch)."""
    values = pd.DataFrame([min_so_far(c, epochs, key) for c in curves], columns=list(epochs))
    return [label] + ["–" if values[e].isna().any() else pm(*mean_std_count(values[e])[:2], digits=3) for e in epochs]
