"""`layout=table2`: the MP-NODE paper's Table 2. Rows MP-NODE finetuned / MP-NODE scratch / L2S (and any other
model); columns are the systems that some run was *finetuned* on (the targets: Lorenz10 ds=50/100/500, Kuramoto
ds=..., Gene, Quadrotors), so pre-training runs in the same directories stay out. Cell: epochs_x_min_error, mean ±
std over seeds. The paper's numbers (`mpsim.report.paper`) and the orderings it claims are printed beside it."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pandas as pd

from mpsim.plotting import save_figure, subplots
from mpsim.report.common import (
    LayoutResult,
    as_numbers,
    column_key,
    family,
    md_table,
    mean_std_count,
    mixed_units,
    norm_scale,
    pm,
    row_label,
    row_order,
    target_systems,
)
from mpsim.report.paper import PAPER_TABLE2


def table2(frame: pd.DataFrame, out_dir: Path) -> LayoutResult:
    """The paper's Table 2: epochs_x_min_error of finetuned vs scratch MP-NODE and L2S on the target systems."""
    train = frame[(frame["task"] == "train") & frame["mode"].isin(["finetune", "scratch"])].copy()
    if train.empty:
        return LayoutResult("No training runs found.", pd.DataFrame(), [])
    targets = sorted(target_systems(train), key=column_key)
    train = train[train["system"].isin(targets)].copy()
    labels = {s: family(s) for s in targets}
    clash = {lab for lab in labels.values() if list(labels.values()).count(lab) > 1}
    labels = {s: (s if lab in clash else lab) for s, lab in labels.items()}
    sizes = train.groupby("system")["n_train"].nunique()
    train["column"] = [
        labels[s] + (f" ds={int(n)}" if sizes[s] > 1 else "")
        for s, n in zip(train["system"], train["n_train"], strict=True)
    ]
    train["row"] = [row_label(*k) for k in zip(train["model_class"], train["mode"], train["variant"], strict=True)]
    records = []
    for (row, column), part in train.groupby(["row", "column"], sort=False):
        mean, std, n = mean_std_count(part["epochs_x_min_error"])
        err, err_sd, _ = mean_std_count(part["min_test_error"])
        ep, ep_sd, _ = mean_std_count(part["min_test_error_epoch"])
        records.append(
            {
                "row": row,
                "column": column,
                "system": part["system"].iloc[0],
                "n_train": part["n_train"].iloc[0],
                "runs": n,
                "epochs_x_min_error": mean,
                "epochs_x_min_error_std": std,
                "min_test_error": err,
                "min_test_error_std": err_sd,
                "min_test_error_epoch": ep,
                "min_test_error_epoch_std": ep_sd,
                "paper": PAPER_TABLE2.get(row, {}).get(column, math.nan),
                "by_seed": _by_seed(part),
                "test_rmse_raw": mean_std_count(as_numbers(part, "test_rmse_raw"))[0],
                "scale": norm_scale(part),
            }
        )
    table = pd.DataFrame(records).drop(columns=["by_seed", "scale"])
    columns = sorted(
        table["column"].unique(), key=lambda c: (column_key(table.loc[table["column"] == c, "system"].iloc[0]), _ds(c))
    )
    rows = sorted(table["row"].unique(), key=row_order)
    cell = {(r["row"], r["column"]): r for r in records}

    def grid(fmt: Callable[[dict], str]) -> str:
        return md_table(
            ["model", *columns], [[r, *[fmt(cell[(r, c)]) if (r, c) in cell else "N/A" for c in columns]] for r in rows]
        )

    paper_rows = [[r, *[_num(PAPER_TABLE2[r].get(c)) for c in columns]] for r in PAPER_TABLE2]
    text = "\n\n".join(
        [
            "**epochs_x_min_error** (epoch of the minimum test error × that error; lower is better), mean ± std over "
            "seeds:",
            grid(lambda r: pm(r["epochs_x_min_error"], r["epochs_x_min_error_std"])),
            "Minimum test error (normalised rollout RMSE) and its epoch:",
            grid(
                lambda r: (
                    f"{pm(r['min_test_error'], r['min_test_error_std'], 3)} @ "
                    f"{pm(r['min_test_error_epoch'], r['min_test_error_epoch_std'], 3)}"
                )
            ),
            "The paper's Table 2 (MPNODE.jl, 4000 epochs for MP-NODE, 10000 for L2S; its own error units):",
            md_table(["model", *columns], paper_rows),
            "Orderings the paper reports:\n" + "\n".join(_orderings(cell, columns)),
            *_unit_notes(cell, columns, rows),
        ]
    )
    return LayoutResult(text, table, [_bars(table, columns, rows, out_dir / "table2.png")])


def _unit_notes(cell: dict, columns: list[str], rows: list[str]) -> list[str]:
    """Where rows of one column were normalised by different stds (a finetune that kept its pre-training's
    normalisation, `mode.refit_normalisation=false`), their normalised errors are in different units: say so and
    give each row's test RMSE in raw units."""
    lines = []
    for c in columns:
        here = [cell[(r, c)] for r in rows if (r, c) in cell and math.isfinite(cell[(r, c)]["scale"])]
        if not mixed_units({r["row"]: r["scale"] for r in here}):
            continue
        stds = ", ".join(f"{r['row']} {r['scale']:.3g}" for r in here)
        raw = ", ".join(f"{r['row']} {r['test_rmse_raw']:.3g}" for r in here)
        lines.append(
            f"- {c}: the rows were normalised by different state stds ({stds}), so their normalised errors and "
            f"epochs_x_min_error are not comparable; in raw units, the best-validation model's test RMSE: {raw}"
        )
    return ["Units:\n" + "\n".join(lines)] if lines else []


def _ds(column: str) -> int:
    return int(column.split("ds=")[1]) if "ds=" in column else 0


def _num(v: Any) -> str:
    return "N/A" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:g}"


def _by_seed(part: pd.DataFrame) -> dict[int, float]:
    """epochs_x_min_error per seed (runs whose summary names no seed are left out)."""
    seeds = pd.to_numeric(part["seed_"], errors="coerce") if "seed_" in part else pd.Series(math.nan, part.index)
    values = pd.to_numeric(part["epochs_x_min_error"], errors="coerce")
    return {int(s): float(v) for s, v in zip(seeds, values, strict=True) if not (math.isnan(s) or math.isnan(v))}


def _paired(fine: dict, scratch: dict) -> str:
    """How many seeds that ran both arms have finetuned < scratch ("" with fewer than two such seeds)."""
    common = sorted(set(fine["by_seed"]) & set(scratch["by_seed"]))
    if len(common) < 2:
        return ""
    wins = sum(fine["by_seed"][k] < scratch["by_seed"][k] for k in common)
    return f"; seed by seed: in {wins} of {len(common)}"


def _orderings(cell: dict, columns: list[str]) -> list[str]:
    """finetuned < scratch in every column (on the means, and seed by seed); MP-NODE < L2S where both ran. With
    variants (`mark_variants`), every finetuned row against every scratch row, and the best MP-NODE row against
    each L2S row."""
    lines = []
    rows = sorted({r for r, _ in cell}, key=row_order)
    fines = [r for r in rows if r.startswith("MP-NODE finetuned")]
    scratches = [r for r in rows if r.startswith("MP-NODE scratch")]
    l2s_rows = [r for r in rows if r == "L2S" or r.startswith("L2S (")]
    for c in columns:
        for f_row in fines:
            for s_row in scratches:
                fine, scratch = cell.get((f_row, c)), cell.get((s_row, c))
                if not (fine and scratch):
                    continue
                plain = (f_row, s_row) == ("MP-NODE finetuned", "MP-NODE scratch")
                f_name, s_name = ("finetuned", "scratch") if plain else (f_row, s_row)
                a, b = fine["epochs_x_min_error"], scratch["epochs_x_min_error"]
                lines.append(
                    f"- {c}: {f_name} {'<' if a < b else '≥'} {s_name} ({a:.4g} vs {b:.4g}, "
                    f"{b / a:.2g}×) — {'holds' if a < b else 'does NOT hold'}{_paired(fine, scratch)}"
                )
        mp = [cell[(r, c)] for r in (*fines, *scratches) if (r, c) in cell]
        best = min(mp, key=lambda r: r["epochs_x_min_error"], default=None)
        for l_row in l2s_rows:
            l2s = cell.get((l_row, c))
            if l2s and best:
                a, b = best["epochs_x_min_error"], l2s["epochs_x_min_error"]
                lines.append(
                    f"- {c}: {best['row']} {'<' if a < b else '≥'} {l_row} ({a:.4g} vs {b:.4g}) — "
                    f"{'holds' if a < b else 'does NOT hold'}"
                )
                ea, eb = best["min_test_error"], l2s["min_test_error"]
                lines.append(f"  (minimum test error: {best['row']} {ea:.3g} vs {l_row} {eb:.3g})")
    return lines or ["- no column has both a finetuned and a scratch run"]


def _bars(table: pd.DataFrame, columns: list[str], rows: list[str], path: Path) -> Path:
    fig, ax = subplots(figsize=(max(6.0, 1.3 * len(columns)), 3.8))
    width = 0.8 / max(len(rows), 1)
    for k, r in enumerate(rows):
        part = table[table["row"] == r].set_index("column")
        xs = [i + (k - (len(rows) - 1) / 2) * width for i, c in enumerate(columns) if c in part.index]
        ys = [part.loc[c, "epochs_x_min_error"] for c in columns if c in part.index]
        es = [
            0.0 if math.isnan(part.loc[c, "epochs_x_min_error_std"]) else part.loc[c, "epochs_x_min_error_std"]
            for c in columns
            if c in part.index
        ]
        ax.bar(xs, ys, width, yerr=es, label=r, capsize=2)
    ax.set_xticks(range(len(columns)), columns, rotation=20, ha="right")
    ax.set(yscale="log", ylabel="epochs × min test error", title="Table 2: lower is better")
    ax.legend(fontsize=8)
    return save_figure(fig, path)
