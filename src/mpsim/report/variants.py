"""Runs that share a layout's place are averaged as seeds only when they ran with the same settings
(`mark_variants`); the settings every report prints as its caption (`settings_caption`)."""

from __future__ import annotations

from typing import Any

import pandas as pd

from mpsim.report.common import as_numbers

#: the facts that place a run in a layout's rows and columns: runs that share them are one experiment's seeds,
#: unless their settings differ (`mark_variants`)
PLACE = ("task", "mode", "system", "trained_on", "model_class", "n_train", "message_size", "zero_messages")


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


def settings_caption(frame: pd.DataFrame) -> str:
    """One line per system: training-set sizes, steps per trajectory, epochs run, seeds."""
    lines = []
    for system, part in frame.groupby("system", sort=True):
        trained = part[part["task"] == "train"] if "task" in part else part
        sizes = sorted({int(v) for v in as_numbers(trained, "n_train").dropna()})
        steps = sorted({int(v) - 1 for v in as_numbers(part, "n_times").dropna()})
        epochs = as_numbers(trained, "epochs_run").dropna()
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
