"""Built-in `mpsim report layout=...` tables and figures of the MP-NODE paper, from any set of run directories.

Each layout reads only what every run records (summary.json, metrics.csv, .hydra/config.yaml), so it works on any
mix of run and sweep directories: runs are sorted into rows and columns by what they are (model class, mode, system,
training-set size, message size), never by where they lie. Every layout takes the frame of runs that
`mark_variants` returns (its `variant` column) and returns Markdown, a long-format table (→ CSV) and writes its PNG
figures.

- ``table2``: the paper's Table 2. Rows MP-NODE finetuned / MP-NODE scratch / L2S (and any other model);
  columns are the systems that some run was *finetuned* on (the targets: Lorenz10 ds=50/100/500, Kuramoto
  ds=..., Gene, Quadrotors), so pre-training runs in the same directories stay out. Cell: epochs_x_min_error,
  mean ± std over seeds. The paper's numbers and the orderings it claims are printed beside it.
- ``table1``: the paper's Table 1 (gene 4×4 trained on BA, zero-shot on unseen ER and WS). Rows are model
  classes; columns are validation and test error on the training system and test error of the zero-shot runs
  on every other system. Where the runs recorded per-step errors, the ratio of each unseen system's test error
  to the training system's at rollout steps 1, 2, 5, 10, ... (`table1_horizons.png`).
- ``curves``: Figure 5, test error per epoch of finetuned vs scratch runs (mean over seeds, min–max band), one
  panel per target system and training-set size, and the epochs each curve needs to reach the best error that
  every curve reaches.
- ``message_size``: Figures 7 and 8, minimum test error against MP-NODE's message size per system, and the
  train-loss / test-error curves per message size; L2S runs on the same system are drawn as a reference.
- ``messages``: Figures 3a and 4, MP-NODE with messages vs `model.zero_messages=true`: minimum train loss and
  test error per arm, their ratio, the train loss by matched epochs, and the train-loss / test-error curves
  (mean over seeds, min–max band).

Runs that share a layout's place (system, model class, mode, training-set size, message size, ...) are averaged as
seeds only when they were run with the same settings: where their resolved configs (`.hydra/config.yaml`, the
model's config as summary.json records it) differ in anything but seeds, places on disk, hardware or what is
written out, `mark_variants` keeps them apart, and every layout's row says how they differ, e.g.
"MP-NODE (model.self_loops=true)".
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd
import yaml

from mpsim.config import host_only, output_only, read_overrides_file
from mpsim.errors import DataError
from mpsim.plotting import at_least_a_factor, save_figure, subplots
from mpsim.safeload import RECORD_BYTES, load_yaml

#: the paper's Table 2 (epochs to the minimum test error × that error; N/A where the paper has none)
PAPER_TABLE2: dict[str, dict[str, float]] = {
    "MP-NODE finetuned": {
        "Lorenz10 ds=50": 632.70,
        "Lorenz10 ds=100": 833.91,
        "Lorenz10 ds=500": 477.75,
        "Kuramoto ds=50": 1358.50,
        "Kuramoto ds=100": 1264.83,
        "Kuramoto ds=500": 874.80,
        "Gene": 12.53,
        "Quadrotors": 236.00,
    },
    "MP-NODE scratch": {
        "Lorenz10 ds=50": 12800,
        "Lorenz10 ds=100": 10454,
        "Lorenz10 ds=500": 5656,
        "Kuramoto ds=50": 5008,
        "Kuramoto ds=100": 5268,
        "Kuramoto ds=500": 3974,
        "Gene": 28,
    },
    "L2S": {"Gene": 46.64, "Quadrotors": 476.0},
}
#: the paper's Table 1 (gene 4×4, trained on BA with 5 adjacency matrices)
PAPER_TABLE1 = {
    "MP-NODE": {
        "Validation BA": "0.0051 ± 0.0001",
        "Test BA": "0.0045 ± 0.0004",
        "Test ER (unseen)": "0.0026 ± 0.0008",
        "Test WS (unseen)": "0.0023 ± 0.0002",
    },
    "L2S": {"Validation BA": "0.0106"},
}
FAMILIES = (("lorenz", None), ("kuramoto", "Kuramoto"), ("gene", "Gene"), ("quad", "Quadrotors"))
MODEL_NAMES = {"MPNODE": "MP-NODE", "L2S": "L2S", "NODE": "NODE"}


@dataclass
class LayoutResult:
    """What a layout produced: Markdown body, a long table for the CSV, and the figures it wrote."""

    markdown: str
    table: pd.DataFrame
    figures: list[Path]


# ---- the runs ----------------------------------------------------------------------------------------------
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


#: the facts that place a run in a layout's rows and columns: runs that share them are one experiment's seeds,
#: unless their settings differ (`mark_variants`)
PLACE = ("task", "mode", "system", "trained_on", "model_class", "n_train", "message_size", "zero_messages")
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


def _with_training(frame: pd.DataFrame) -> list[Any]:
    """Each run's settings; a zero-shot run's joined by the trainer and mode settings of the training run whose
    checkpoint it evaluated (its `init` is that run's export or best checkpoint), when that run is in the frame,
    so that two models trained differently stay apart in the zero-shot columns too."""
    settings = list(frame["settings"])
    if "made_" not in frame or "init_" not in frame:
        return settings
    made: dict[str, dict[str, str]] = {}
    for s, paths, mode in zip(settings, frame["made_"], frame["mode"], strict=True):
        if mode != "zeroshot" and isinstance(s, dict) and isinstance(paths, list):
            made |= {p: s for p in paths}
    for k, (s, init, mode) in enumerate(zip(settings, frame["init_"], frame["mode"], strict=True)):
        source = made.get(init) if mode == "zeroshot" and isinstance(init, str) else None
        if source is not None and isinstance(s, dict):
            settings[k] = {key: v for key, v in source.items() if key.startswith(("trainer.", "mode."))} | s
    return settings


def _fact(value: Any) -> str:
    return str(int(value)) if isinstance(value, float) and value.is_integer() else str(value)


def mark_variants(frame: pd.DataFrame) -> tuple[pd.DataFrame, list[str]]:
    """Add `variant` to a frame of runs (with a `settings` column from `run_settings`, which this drops): among
    runs that share a place (`PLACE`), the settings in which they differ, as " (key=value, ...)", so a layout
    keeps them apart instead of averaging them as seeds; "" where they agree. A key some runs lack (written by an
    older mpsim) counts only if the runs that have it disagree. Also returns one note per place so split."""
    frame = frame.copy()
    for column in PLACE:  # summaries of other tasks (bench, simulate) lack them: such runs place nowhere
        if column not in frame:
            frame[column] = None
    frame["variant"] = ""
    notes: list[str] = []
    if "settings" not in frame:
        return frame, notes
    frame["settings"] = _with_training(frame)
    place = [c for c in PLACE if c in frame]
    keyed = frame[place].map(str)  # one text per fact, a missing one included ("nan", "None")
    for _, index in keyed.groupby(place, sort=False, dropna=False).groups.items():
        if len(index) < 2:
            continue
        settings = [s if isinstance(s, dict) else {} for s in frame.loc[index, "settings"]]
        keys = sorted({k for s in settings for k in s})
        differ = [k for k in keys if len({s[k] for s in settings if k in s}) > 1]
        if not differ:
            continue
        for i, s in zip(index, settings, strict=True):
            frame.at[i, "variant"] = " (" + ", ".join(f"{k}={s.get(k, '?')}" for k in differ) + ")"
        first = frame.loc[index[0]]
        where = ", ".join(
            f"{c} {_fact(first[c])}"
            for c in ("system", "model_class", "mode", "n_train", "trained_on")
            if c in first and pd.notna(first[c])
        )
        notes.append(
            f"- {len(index)} runs ({where}) differ in {', '.join(f'`{k}`' for k in differ)}: kept apart, not "
            "averaged as seeds"
        )
    return frame.drop(columns=["settings", *(c for c in ("made_", "init_") if c in frame)]), notes


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


def _stats(values: pd.Series) -> tuple[float, float, int]:
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


def _numbers(frame: pd.DataFrame, column: str) -> pd.Series:
    """`frame[column]` as numbers (NaN where not one); all NaN where no run recorded the column."""
    if column not in frame:
        return pd.Series(math.nan, index=frame.index, dtype=float)
    return pd.to_numeric(frame[column], errors="coerce")


def settings_caption(frame: pd.DataFrame) -> str:
    """One line per system: training-set sizes, steps per trajectory, epochs run, seeds."""
    lines = []
    for system, part in frame.groupby("system", sort=True):
        trained = part[part["task"] == "train"] if "task" in part else part
        sizes = sorted({int(v) for v in _numbers(trained, "n_train").dropna()})
        steps = sorted({int(v) - 1 for v in _numbers(part, "n_times").dropna()})
        epochs = _numbers(trained, "epochs_run").dropna()
        seeds = (
            sorted({int(s) for s in pd.to_numeric(part["seed_"], errors="coerce").dropna()}) if "seed_" in part else []
        )
        bits = [f"{len(part)} run{'s' if len(part) > 1 else ''}"]
        if sizes:
            bits.append(f"{'/'.join(map(str, sizes))} training trajectories")
        if steps:
            bits.append(f"{'/'.join(map(str, steps))} steps")
        if len(epochs):
            bits.append(f"up to {int(epochs.max())} epochs")
        if seeds:
            bits.append(f"seed{'s' if len(seeds) > 1 else ''} {', '.join(map(str, seeds))}")
        devices = trained["device"].dropna().astype(str).value_counts() if "device" in trained else pd.Series(dtype=int)
        if len(devices):  # wall times are only comparable between runs on the same device
            unknown = len(trained) - int(devices.sum())  # summaries from before `device` was recorded
            counted = len(devices) > 1 or unknown > 0
            where = " / ".join(f"{d}{f' ×{n}' if counted else ''}" for d, n in devices.items())
            bits.append(f"on {where}" + (f" (device not recorded for {unknown})" if unknown else ""))
        lines.append(f"- `{system}`: {', '.join(bits)}")
    return "\n".join(lines)


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


def _targets(train: pd.DataFrame) -> list[str]:
    """Systems some run was finetuned on (all systems when none was)."""
    fine = sorted(set(train.loc[train["mode"] == "finetune", "system"]))
    return fine or sorted(set(train["system"]))


def _column_key(system: str) -> tuple[int, str]:
    order = {label or "Lorenz": k for k, (_, label) in enumerate(FAMILIES)}
    fam = family(system)
    return (order.get("Lorenz" if fam.lower().startswith("lorenz") else fam, len(order)), system)


# ---- table 2 -----------------------------------------------------------------------------------------------
def table2(frame: pd.DataFrame, out_dir: Path) -> LayoutResult:
    """The paper's Table 2: epochs_x_min_error of finetuned vs scratch MP-NODE and L2S on the target systems."""
    train = frame[(frame["task"] == "train") & frame["mode"].isin(["finetune", "scratch"])].copy()
    if train.empty:
        return LayoutResult("No training runs found.", pd.DataFrame(), [])
    targets = sorted(_targets(train), key=_column_key)
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
        mean, std, n = _stats(part["epochs_x_min_error"])
        err, err_sd, _ = _stats(part["min_test_error"])
        ep, ep_sd, _ = _stats(part["min_test_error_epoch"])
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
                "test_rmse_raw": _stats(_numbers(part, "test_rmse_raw"))[0],
                "scale": _scale(part),
            }
        )
    table = pd.DataFrame(records).drop(columns=["by_seed", "scale"])
    columns = sorted(
        table["column"].unique(), key=lambda c: (_column_key(table.loc[table["column"] == c, "system"].iloc[0]), _ds(c))
    )
    rows = sorted(table["row"].unique(), key=_row_order)
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


def _scale(part: pd.DataFrame) -> float:
    """Raw over normalised test RMSE, mean over runs: the state std each run's errors are divided by. Only for
    one-feature systems (gene), where the ratio is that std exactly; NaN otherwise."""
    if "test_rmse_raw" not in part or not (_numbers(part, "n_features") == 1).all():
        return math.nan
    ratio = pd.to_numeric(part["test_rmse_raw"], errors="coerce") / pd.to_numeric(part["test_rmse"], errors="coerce")
    ratio = ratio[ratio > 0]
    return float(ratio.mean()) if len(ratio) else math.nan


def _run_scale(run: dict[str, Any]) -> float:
    """One run's raw over normalised test RMSE (its state std on a one-feature system)."""
    return float(run["test_rmse_raw"]) / float(run["test_rmse"])


def _mixed_units(scales: dict[str, float]) -> bool:
    """Whether rows (row → `_scale`) were normalised by stds more than 1 % apart; False where one is unknown."""
    values = list(scales.values())
    return len(values) > 1 and all(math.isfinite(v) for v in values) and max(values) > 1.01 * min(values)


def _unit_notes(cell: dict, columns: list[str], rows: list[str]) -> list[str]:
    """Where rows of one column were normalised by different stds (a finetune that kept its pre-training's
    normalisation, `mode.refit_normalisation=false`), their normalised errors are in different units: say so and
    give each row's test RMSE in raw units."""
    lines = []
    for c in columns:
        here = [cell[(r, c)] for r in rows if (r, c) in cell and math.isfinite(cell[(r, c)]["scale"])]
        if not _mixed_units({r["row"]: r["scale"] for r in here}):
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


def _row_order(row: str) -> tuple[int, str]:
    """Finetuned, scratch, L2S (each with its variants, `mark_variants`), then any other model."""
    order = ["MP-NODE finetuned", "MP-NODE scratch", "L2S"]
    base = next((k for k, o in enumerate(order) if row == o or row.startswith(f"{o} (")), len(order))
    return (base, row)


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
    rows = sorted({r for r, _ in cell}, key=_row_order)
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


# ---- table 1 -----------------------------------------------------------------------------------------------
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
    paper_cols = ["Validation BA", "Test BA", "Test ER (unseen)", "Test WS (unseen)"]
    paper = md_table(
        ["model", *paper_cols], [[r, *[v.get(c, "N/A") for c in paper_cols]] for r, v in PAPER_TABLE1.items()]
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


#: the paper's Table 1 ratios of the unseen graphs' test error to BA's (MP-NODE): ER 0.0026 / 0.0045, WS 0.0023 / 0.0045
PAPER_TABLE1_RATIOS = {"ER": 0.0026 / 0.0045, "WS": 0.0023 / 0.0045}


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
        base = [_stats(part[f"test_rmse_step{k}"])[0] for k in steps]
        if not any(b > 0 for b in base):  # this model's training runs recorded no per-step errors
            continue
        rows.append([f"{name}: {fam} test RMSE", *[f"{b:.3g}" if b > 0 else "–" for b in base], ""])
        mine = unseen[(unseen["model_class"] == cls) & (unseen["variant"] == variant)]
        for system, zpart in mine.groupby("system"):
            g = graph_family(str(system))
            ratio = [
                _stats(zpart[f"test_rmse_step{k}"])[0] / b if b > 0 else math.nan
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
    mean, std, n = _stats(values)
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


# ---- curves (figure 5) -------------------------------------------------------------------------------------
def curves(frame: pd.DataFrame, out_dir: Path) -> LayoutResult:
    """Figure 5: test error per epoch, finetuned vs scratch, per target system and training-set size."""
    train = frame[(frame["task"] == "train") & frame["mode"].isin(["finetune", "scratch"])].copy()
    if train.empty:
        return LayoutResult("No training runs found.", pd.DataFrame(), [])
    train = train[train["system"].isin(_targets(train))].copy()
    train["row"] = [row_label(*k) for k in zip(train["model_class"], train["mode"], train["variant"], strict=True)]
    panels = sorted(train.groupby(["system", "n_train"]).groups, key=lambda k: (_column_key(k[0]), k[1]))
    n_col = min(3, len(panels))
    n_row = math.ceil(len(panels) / n_col)
    fig, axes = subplots(n_row, n_col, figsize=(4.2 * n_col, 3.2 * n_row), squeeze=False, layout="constrained")
    records, sections = [], []
    for ax, (system, n_train) in zip(axes.flat, panels, strict=False):
        part = train[(train["system"] == system) & (train["n_train"] == n_train)]
        scales = {row: _scale(runs) for row, runs in part.groupby("row")}
        raw = _mixed_units(scales)  # rows normalised differently: compare them in raw units
        means = {}
        for row, runs in sorted(part.groupby("row"), key=lambda kv: _row_order(kv[0])):
            loaded = [
                c.assign(test_error=c["test_error"] * (_run_scale(fact) if raw else 1.0))
                for fact in runs.to_dict("records")
                if (c := read_metrics(fact["run"])) is not None
            ]
            if not loaded:
                continue
            wide = _mean_band(ax, loaded, "test_error", f"{row} ({len(loaded)})")
            mean = wide.mean(axis=1)
            means[row] = mean
            records += [
                {
                    "system": system,
                    "n_train": n_train,
                    "row": row,
                    "epoch": int(e),
                    "test_error_mean": v,
                    "test_error_std": wide.loc[e].std(),
                    "runs": len(loaded),
                }
                for e, v in mean.items()
            ]
        unit = " (raw units)" if raw else ""
        ax.set(yscale="log", xlabel="epoch", ylabel=f"test rollout RMSE{unit}", title=f"{system}, ds={n_train}")
        ax.legend(fontsize=7)
        section = _reach_table(system, n_train, means)
        if raw:
            stds = ", ".join(f"{row} {v:.3g}" for row, v in sorted(scales.items(), key=lambda kv: _row_order(kv[0])))
            section += (
                f"\n\nErrors in raw units (each run's normalised error × its state std): the rows were normalised "
                f"by different stds ({stds})."
            )
        sections.append(section)
    for ax in list(axes.flat)[len(panels) :]:
        ax.axis("off")
    fig.suptitle("Finetuned vs from scratch (mean over seeds, band: min–max)")
    figure = save_figure(fig, out_dir / "curves.png")
    return LayoutResult("\n\n".join(sections), pd.DataFrame(records), [figure])


def _mean_band(ax: Any, curves: Sequence[pd.DataFrame], key: str, label: str, color: str | None = None) -> pd.DataFrame:
    """Draw the mean of `key` per epoch over the runs' curves with a min–max band; return the runs side by side."""
    wide = pd.concat([c.set_index("epoch")[key] for c in curves], axis=1)  # [epoch, run]
    mean = wide.mean(axis=1)
    (line,) = ax.plot(mean.index, mean.values, color=color, label=label)
    ax.fill_between(mean.index, wide.min(axis=1), wide.max(axis=1), color=line.get_color(), alpha=0.2)
    return wide


def _reach_table(system: str, n_train: Any, means: dict[str, pd.Series]) -> str:
    """Epochs each mean curve needs to reach the best error that every curve reaches."""
    trained = {k: v[v.index >= 1] for k, v in means.items() if (v.index >= 1).any()}
    if not trained:
        return f"**{system}, ds={n_train}**: no curves."
    level = max(float(v.min()) for v in trained.values())
    rows = []
    for k, v in trained.items():
        reach = v[v <= level]
        rows.append(
            [
                k,
                f"{float(means[k].iloc[0]):.3g}",
                int(reach.index[0]) if len(reach) else "never",
                f"{float(v.min()):.3g} @ {int(v.idxmin())}",
            ]
        )
    head = f"**{system}, ds={n_train}** — target: {level:.3g}, the best mean test error every curve reaches"
    return head + "\n\n" + md_table(["run", "epoch-0 error", "epochs to target", "min mean error @ epoch"], rows)


# ---- message size (figures 7, 8) ---------------------------------------------------------------------------
def _checkpoint_epochs(curves: Sequence[pd.DataFrame]) -> list[int]:
    """The quarters of the longest run (1000/2000/3000/4000 for 4000 epochs): where runs are compared."""
    last = max((int(c["epoch"].max()) for c in curves), default=0)
    return sorted({max(1, round(last * q / 4)) for q in (1, 2, 3, 4)}) if last >= 1 else []


def min_so_far(curve: pd.DataFrame, epochs: Sequence[int], key: str = "test_error") -> list[float]:
    """The curve's minimum `key` over epochs 1..e for each e (NaN where the run stopped before e)."""
    trained = curve[curve["epoch"] >= 1].set_index("epoch")[key].sort_index().cummin()
    return [float(trained[trained.index <= e].iloc[-1]) if trained.index.max() >= e else math.nan for e in epochs]


def _by_epoch_row(
    label: Any, curves: Sequence[pd.DataFrame], epochs: Sequence[int], key: str = "test_error"
) -> list[Any]:
    values = pd.DataFrame([min_so_far(c, epochs, key) for c in curves], columns=list(epochs))
    return [label] + ["–" if values[e].isna().any() else pm(*_stats(values[e])[:2], digits=3) for e in epochs]


def _size_stats(label: str, runs: pd.DataFrame, curves: list[pd.DataFrame]) -> tuple[dict[str, Any], list[Any]]:
    """One message-size table entry (MP-NODE at one size, or L2S) over its seeds: the report.csv fields and the
    Markdown row (min test error, final train loss, epochs_x_min_error, mean ± std)."""
    err, err_sd, n = _stats(runs["min_test_error"])
    exm, exm_sd, _ = _stats(runs["epochs_x_min_error"])
    loss, loss_sd, _ = _stats(pd.Series([float(c["train_loss"].iloc[-1]) for c in curves]))
    stats = {
        "runs": n,
        "min_test_error": err,
        "min_test_error_std": err_sd,
        "epochs_x_min_error": exm,
        "epochs_x_min_error_std": exm_sd,
        "final_train_loss": loss,
        "final_train_loss_std": loss_sd,
    }
    return stats, [label, n, pm(err, err_sd, 3), pm(loss, loss_sd, 3), pm(exm, exm_sd, 4)]


def message_size(frame: pd.DataFrame, out_dir: Path) -> LayoutResult:
    """Figures 7 and 8: MP-NODE's minimum test error and learning curves per message size, per system."""
    train = frame[(frame["task"] == "train") & (frame["mode"] != "zeroshot")].copy()  # zero-shot runs train nothing
    mp = train[(train["model_class"] == "MPNODE") & train["message_size"].notna()]
    if mp.empty:
        return LayoutResult("No MP-NODE training runs found.", pd.DataFrame(), [])
    records, sections = [], []
    systems = sorted(mp["system"].unique(), key=_column_key)
    fig, axes = subplots(1, len(systems), figsize=(4.2 * len(systems), 3.4), squeeze=False, layout="constrained")
    cfig, caxes = subplots(2, len(systems), figsize=(4.2 * len(systems), 6.2), squeeze=False, layout="constrained")
    for k, system in enumerate(systems):
        part = mp[mp["system"] == system]
        rows, by_epoch = [], []
        # compared at the quarters of the longest MP-NODE run (L2S may run longer: 10000 epochs against 4000)
        curves = {r: c for r in part["run"] if (c := read_metrics(r)) is not None}  # each metrics.csv read once
        epochs = _checkpoint_epochs(list(curves.values()))
        panels = (("train_loss", caxes[0, k]), ("test_error", caxes[1, k]))  # the curves figure's column
        for (m, variant), runs in sorted(
            part.groupby(["message_size", "variant"]), key=lambda kv: (int(kv[0][0]), kv[0][1])
        ):
            loaded = [curves[r] for r in runs["run"] if r in curves]
            label = f"{int(m)}{variant}"
            stats, row = _size_stats(label, runs, loaded)
            records.append({"system": system, "message_size": int(m), "variant": variant.strip(" ()")} | stats)
            rows.append(row)
            if loaded and epochs:
                by_epoch.append(_by_epoch_row(label, loaded, epochs))
            for key, ax in panels:
                if loaded:
                    mean = pd.concat([c.set_index("epoch")[key] for c in loaded], axis=1).mean(axis=1).dropna()
                    ax.plot(mean.index, mean.values, label=f"m={label}")
        table = pd.DataFrame([r for r in records if r["system"] == system])
        for variant, vt in table.groupby("variant", sort=False):
            axes[0, k].errorbar(
                vt["message_size"],
                vt["min_test_error"],
                yerr=vt["min_test_error_std"].fillna(0.0),
                marker="o",
                capsize=3,
                label=f"MP-NODE ({variant})" if variant else "MP-NODE",
            )
        l2s_all = train[(train["system"] == system) & (train["model_class"] == "L2S")]
        for variant, l2s in l2s_all.groupby("variant", sort=False):
            name = f"L2S{variant}"
            l2s_curves = [c for c in (read_metrics(r) for r in l2s["run"]) if c is not None]
            stats, row = _size_stats(name, l2s, l2s_curves)
            axes[0, k].axhline(stats["min_test_error"], color="black", linestyle="--", label=name)
            records.append({"system": system, "message_size": None, "model": name} | stats)
            rows.append(row)
            for i, c in enumerate(l2s_curves):  # each seed its own dashed line, named once in the legend
                for key, ax in panels:
                    seed_label = name if i == 0 else None
                    ax.plot(c["epoch"], c[key], color="black", linestyle="--", linewidth=0.8, label=seed_label)
            if l2s_curves and epochs:
                by_epoch.append(_by_epoch_row(name, l2s_curves, epochs))
        axes[0, k].set(xlabel="message size", ylabel="min test rollout RMSE", title=system, yscale="log")
        at_least_a_factor(axes[0, k], 4.0)
        axes[0, k].legend(fontsize=8)
        caxes[0, k].set(yscale="log", ylabel="train loss", title=system)
        caxes[1, k].set(yscale="log", xlabel="epoch", ylabel="test rollout RMSE")
        caxes[0, k].legend(fontsize=8)
        sections.append(
            f"**{system}**\n\n"
            + md_table(["message size", "runs", "min test error", "final train loss", "epochs_x_min_error"], rows)
        )
        if by_epoch:  # matched epochs: is the order the same at every stage of training, or only at the end?
            sections.append(
                f"Minimum test error so far, by epoch ({system}; – where a run stopped earlier):\n\n"
                + md_table(["message size", *(f"by epoch {e}" for e in epochs)], by_epoch)
            )
    fig.suptitle("Effect of message size (Figure 8; Figure 7 for quadrotors)")
    cfig.suptitle("Train loss and test error per message size (mean over seeds; L2S dashed black, one line per seed)")
    figures = [save_figure(fig, out_dir / "message_size.png"), save_figure(cfig, out_dir / "message_size_curves.png")]
    return LayoutResult("\n\n".join(sections), pd.DataFrame(records), figures)


# ---- messages on vs off (figures 3a, 4) --------------------------------------------------------------------
def messages(frame: pd.DataFrame, out_dir: Path) -> LayoutResult:
    """Figures 3a and 4: MP-NODE with messages vs `model.zero_messages=true` (each node an augmented NODE)."""
    train = frame[
        (frame["task"] == "train") & (frame["mode"] != "zeroshot") & (frame["model_class"] == "MPNODE")
    ].copy()
    if train.empty:
        return LayoutResult("No MP-NODE training runs found.", pd.DataFrame(), [])
    train["off"] = train["zero_messages"].map(lambda v: v is True)  # a config without the flag: messages on
    systems = sorted(train["system"].unique(), key=_column_key)
    width = max(6.0, 4.2 * len(systems))
    fig, axes = subplots(2, len(systems), figsize=(width, 6.2), squeeze=False, layout="constrained")
    records, sections = [], []
    for k, system in enumerate(systems):
        part = train[train["system"] == system]
        curves = {r: c for r in part["run"] if (c := read_metrics(r)) is not None}  # each metrics.csv read once
        epochs = _checkpoint_epochs(list(curves.values()))
        rows, by_epoch, cell = [], [], {}
        # messages on first
        for (off, variant), runs in sorted(part.groupby(["off", "variant"]), key=lambda kv: (bool(kv[0][0]), kv[0][1])):
            label = ("off (`zero_messages=true`)" if off else "on") + variant
            loaded = [curves[r] for r in runs["run"] if r in curves]
            loss = _stats(pd.Series([float(c.loc[c["epoch"] >= 1, "train_loss"].min()) for c in loaded]))
            err = _stats(runs["min_test_error"])
            exm = _stats(runs["epochs_x_min_error"])
            cell[(bool(off), variant)] = (loss[0], err[0])
            records.append(
                {
                    "system": system,
                    "messages": "off" if off else "on",
                    "variant": variant.strip(" ()"),
                    "runs": err[2],
                    "min_train_loss": loss[0],
                    "min_train_loss_std": loss[1],
                    "min_test_error": err[0],
                    "min_test_error_std": err[1],
                    "epochs_x_min_error": exm[0],
                    "epochs_x_min_error_std": exm[1],
                }
            )
            rows.append([label, err[2], pm(*loss[:2], digits=3), pm(*err[:2], digits=3), pm(*exm[:2], digits=4)])
            if loaded and epochs:
                by_epoch.append(_by_epoch_row(label, loaded, epochs, "train_loss"))
            colour = "tab:blue" if off else "tab:red"  # the paper's Figure 3a: on red, off blue
            name = ("messages off (zero_messages=true)" if off else "messages on") + variant
            for key, ax in (("train_loss", axes[0, k]), ("test_error", axes[1, k])):
                if loaded:
                    _mean_band(ax, loaded, key, f"{name} ({len(loaded)})", colour)
        axes[0, k].set(yscale="log", ylabel="train loss", title=system)
        axes[1, k].set(yscale="log", xlabel="epoch", ylabel="test rollout RMSE")
        axes[0, k].legend(fontsize=7)
        text = f"**{system}**\n\n" + md_table(
            ["messages", "runs", "min train loss", "min test error", "epochs_x_min_error"], rows
        )
        for variant in sorted({v for _, v in cell}):  # on against off, where both ran with the same settings
            if (True, variant) in cell and (False, variant) in cell:
                (loss_on, err_on), (loss_off, err_off) = cell[(False, variant)], cell[(True, variant)]
                holds = loss_on < loss_off and err_on < err_off
                text += (
                    f"\n\nMessages off / on{variant}: train loss {loss_off / loss_on:.3g}×, test error "
                    f"{err_off / err_on:.3g}× — messages {'lower' if holds else 'do NOT lower'} both (the paper's "
                    "Figure 3a: lower training loss with messages on)"
                )
        sections.append(text)
        if by_epoch:  # is the order the same at every stage of training?
            sections.append(
                f"Minimum train loss so far, by epoch ({system}; – where a run stopped earlier):\n\n"
                + md_table(["messages", *(f"by epoch {e}" for e in epochs)], by_epoch)
            )
    fig.suptitle("Messages on vs off (Figure 3a; Figure 4 for Kuramoto): mean over seeds, band min–max")
    return LayoutResult("\n\n".join(sections), pd.DataFrame(records), [save_figure(fig, out_dir / "messages.png")])


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
