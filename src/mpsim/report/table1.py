"""`layout=table1`: the MP-NODE paper's Table 1 (gene 4×4 trained on BA, zero-shot on unseen ER and WS). Rows are
model classes; columns are validation and test error on the training system and test error of the zero-shot runs
on every other system. Where the runs recorded per-step errors, the ratio of each unseen system's test error to
the training system's at rollout steps 1, 2, 5, 10, ... (`table1_horizons.png`)."""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd

from mpsim.plotting import save_figure, subplots
from mpsim.report.common import LayoutResult, graph_family, md_table, mean_std_count, model_name, pm
from mpsim.report.paper import PAPER_TABLE1, PAPER_TABLE1_COLUMNS, PAPER_TABLE1_RATIOS
from mpsim.report.runs import STEPS


def table1(frame: pd.DataFrame, out_dir: Path) -> LayoutResult:
    """The paper's Table 1: validation/test error on the training graphs and zero-shot error on unseen ones."""
    train = frame[(frame["task"] == "train") & (frame["mode"] == "scratch")]
    zero = frame[frame["mode"] == "zeroshot"]
    if train.empty:
        return LayoutResult("No training runs found.", pd.DataFrame(), [])
    home = train["system"].mode().iloc[0] if train["system"].nunique() > 1 else train["system"].iloc[0]
    if len(zero):  # the system the zero-shot checkpoints were trained on
        home = zero["trained_on"].dropna().mode().iloc[0] if zero["trained_on"].notna().any() else home
    fam = graph_family(home)
    records = []
    for (cls, variant), part in train[train["system"] == home].groupby(["model_class", "variant"]):
        name = model_name(cls, variant)
        for column, values in ((f"Validation {fam}", part["best_val_error"]), (f"Test {fam}", part["test_rmse"])):
            records.append({"row": name, "column": column, "system": home, **_named_stats(values)})
    unseen = zero[(zero["trained_on"] == home) & (zero["system"] != home)]
    for (cls, variant, system), part in unseen.groupby(["model_class", "variant", "system"]):
        name = model_name(cls, variant)
        records.append(
            {
                "row": name,
                "column": f"Test {graph_family(system)} (unseen)",
                "system": system,
                **_named_stats(part["test_rmse"]),
            }
        )
    table = pd.DataFrame(records)
    columns = list(dict.fromkeys(table["column"]))
    rows = sorted(table["row"].unique(), key=lambda r: (not r.startswith("MP-NODE"), r))
    cell = {(r["row"], r["column"]): r for r in records}
    ours = md_table(
        ["model", *columns],
        [
            [r, *[pm(cell[(r, c)]["mean"], cell[(r, c)]["std"], 3) if (r, c) in cell else "N/A" for c in columns]]
            for r in rows
        ],
    )
    paper = md_table(
        ["model", *PAPER_TABLE1_COLUMNS],
        [[r, *[v.get(c, "N/A") for c in PAPER_TABLE1_COLUMNS]] for r, v in PAPER_TABLE1.items()],
    )
    checks = []
    mp_rows = [r for r in rows if r.startswith("MP-NODE")]
    for mp in mp_rows:
        base = cell.get((mp, f"Test {fam}"))
        for c in columns:
            z = cell.get((mp, c))
            if base and z and "unseen" in c:
                ratio = z["mean"] / base["mean"]
                verdict = "same order" if 0.1 <= ratio <= 10 else "NOT the same order"
                who = f"{mp}, " if len(mp_rows) > 1 else ""
                checks.append(f"- {who}{c}: {ratio:.2g}× the error on {fam} test data — {verdict} of magnitude")
    for mp in mp_rows:
        for l2s in (r for r in rows if r.startswith("L2S")):
            val_mp, val_l2s = cell.get((mp, f"Validation {fam}")), cell.get((l2s, f"Validation {fam}"))
            if val_mp and val_l2s:
                holds = val_mp["mean"] < val_l2s["mean"]
                checks.append(
                    f"- validation: {mp} {val_mp['mean']:.3g} {'<' if holds else '≥'} {l2s} {val_l2s['mean']:.3g} "
                    f"— {'holds' if holds else 'does NOT hold'}"
                )
    figures = [_error_bars(table, columns, rows, out_dir / "table1.png")]
    by_step = _zero_shot_by_step(train[train["system"] == home], unseen, fam, out_dir)
    parts = [
        f"Trained on `{home}`; errors are normalised rollout RMSE over the full horizon (validation: the best "
        "epoch's; test: the best checkpoint's), mean ± std over seeds:",
        ours,
        "The paper's Table 1 (its own error units, likely a squared error; compare orders and ratios, not values):",
        paper,
        "Checks:\n" + ("\n".join(checks) if checks else "- nothing to compare"),
    ]
    if by_step is not None:
        parts.append(by_step[0])
        figures.append(by_step[1])
    return LayoutResult("\n\n".join(parts), table, figures)


def _crossing(steps: list[int], ratio: list[float], fam: str) -> str:
    """In words, at which of the listed steps a ratio to the training graph's error is below 1 and where not:
    "easier than BA at steps 1–2, harder at 5–10, easier at 20–50"."""
    easier = [r < 1 for r in ratio]
    if all(easier):
        return f"easier than {fam} at every listed step (the paper's direction)"
    if not any(easier):
        return f"harder than {fam} at every listed step"
    spans: list[list[int]] = []  # runs of consecutive listed steps on the same side of 1
    for i, e in enumerate(easier):
        if i and e == easier[i - 1]:
            spans[-1].append(steps[i])
        else:
            spans.append([steps[i]])
    words: list[str] = []
    side = easier[0]
    for span in spans:
        at = f"step {span[0]}" if len(span) == 1 else f"steps {span[0]}–{span[-1]}"
        words.append(f"{'easier' if side else 'harder'} {'than ' + fam + ' ' if not words else ''}at {at}")
        side = not side
    return ", ".join(words)


def _zero_shot_by_step(home: pd.DataFrame, unseen: pd.DataFrame, fam: str, out_dir: Path) -> tuple[str, Path] | None:
    """The zero-shot ratios (unseen graph's test RMSE / the training graph's, means over seeds) after k rollout
    steps, per model: whether the unseen graphs are easier than the training graph depends on how far the
    rollout has run. None when the runs recorded no per-step errors."""
    steps = [k for k in STEPS if f"test_rmse_step{k}" in home and f"test_rmse_step{k}" in unseen]
    steps = [
        k for k in steps if home[f"test_rmse_step{k}"].notna().any() and unseen[f"test_rmse_step{k}"].notna().any()
    ]
    if not steps or unseen.empty:
        return None
    rows: list[list[str]] = []
    checks: list[str] = []
    curves: dict[str, tuple[list[int], list[float]]] = {}
    for (cls, variant), part in home.groupby(["model_class", "variant"]):
        name = model_name(cls, variant)
        base = [mean_std_count(part[f"test_rmse_step{k}"])[0] for k in steps]
        if not any(b > 0 for b in base):  # this model's training runs recorded no per-step errors
            continue
        rows.append([f"{name}: {fam} test RMSE", *[f"{b:.3g}" if b > 0 else "–" for b in base], ""])
        mine = unseen[(unseen["model_class"] == cls) & (unseen["variant"] == variant)]
        for system, zpart in mine.groupby("system"):
            g = graph_family(str(system))
            ratio = [
                mean_std_count(zpart[f"test_rmse_step{k}"])[0] / b if b > 0 else math.nan
                for k, b in zip(steps, base, strict=True)
            ]
            known = [(k, r) for k, r in zip(steps, ratio, strict=True) if math.isfinite(r)]
            if not known:
                continue
            paper = PAPER_TABLE1_RATIOS.get(g) if name.startswith("MP-NODE") else None
            cells = [f"{r:.2f}" if math.isfinite(r) else "–" for r in ratio]
            rows.append([f"{name}: {g} / {fam}", *cells, "" if paper is None else f"{paper:.2f}"])
            curves[f"{name} {g} / {fam}"] = ([k for k, _ in known], [r for _, r in known])
            checks.append(f"- {name} on {g} (unseen): {_crossing([k for k, _ in known], [r for _, r in known], fam)}")
    if not rows:
        return None
    header = ["ratio by rollout step", *map(str, steps), "paper (full horizon)"]
    text = "\n\n".join(
        [
            "Zero-shot by rollout horizon: the unseen graph's test RMSE at rollout step k over the training graph's "
            "(ratio of the means over seeds; below 1: the unseen graph is easier, as the paper found at the full horizon):",
            md_table(header, rows),
            "\n".join(checks),
        ]
    )
    fig, ax = subplots(figsize=(5.6, 3.6))
    for label, (at, ratio) in curves.items():
        ax.plot(at, ratio, marker="o", label=label)
    for g, r in PAPER_TABLE1_RATIOS.items():
        ax.plot([steps[-1]], [r], marker="*", markersize=11, linestyle="none", label=f"paper MP-NODE {g} / {fam}")
    ax.axhline(1.0, color="grey", linewidth=0.8, linestyle="--")
    ax.set(xscale="log", xlabel="rollout step", ylabel=f"test RMSE / {fam} test RMSE", title="Zero-shot by horizon")
    ax.legend(fontsize=7)
    return text, save_figure(fig, out_dir / "table1_horizons.png")


def _named_stats(values: pd.Series) -> dict[str, float]:
    mean, std, n = mean_std_count(values)
    return {"mean": mean, "std": std, "runs": n}


def _error_bars(table: pd.DataFrame, columns: list[str], rows: list[str], path: Path) -> Path:
    fig, ax = subplots(figsize=(max(5.0, 1.4 * len(columns)), 3.6))
    width = 0.8 / max(len(rows), 1)
    for k, r in enumerate(rows):
        part = table[table["row"] == r].set_index("column")
        xs = [i + (k - (len(rows) - 1) / 2) * width for i, c in enumerate(columns) if c in part.index]
        ys = [part.loc[c, "mean"] for c in columns if c in part.index]
        es = [0.0 if math.isnan(part.loc[c, "std"]) else part.loc[c, "std"] for c in columns if c in part.index]
        ax.bar(xs, ys, width, yerr=es, label=r, capsize=2)
    ax.set_xticks(range(len(columns)), columns, rotation=15, ha="right")
    ax.set(ylabel="rollout RMSE (normalised)", title="Table 1: zero-shot generalisation")
    ax.legend(fontsize=8)
    return save_figure(fig, path)
