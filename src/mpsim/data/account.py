"""Every sample accounted for: what the steps of `mpsim.data.measured` did to each file's rows, said in the
file's terms (its name, rows and times), for the console, `summary.json` and `diagnosis.md`.

The account (``meta["account"]``, plain data) holds the path given and whether it was a pattern, and per file: the
rows read, the span of its times, each gap in its clock (``split`` or ``filled``), and each piece between gaps with
the samples it has on the grid used (after `data.resample` / `data.stride`), the segments cut from it and the
samples they use, or why it was not used. `account_lines` words it; `split_lines` words what each split covers.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from mpsim.data.clipped import clipped_text

#: files named one by one before "and N more"
SHOWN_FILES = 8


def account_lines(account: Mapping[str, Any]) -> list[str]:
    """The account, one line per file (and one for the pattern): what was read, split, filled, left out."""
    files = list(account.get("files", []))
    lines = []
    head = f"data ({account['part']})" if account.get("part") else "data"
    if account.get("pattern"):
        names = [Path(f["file"]).name for f in files]
        more = len(names) - SHOWN_FILES
        shown = ", ".join(names[:SHOWN_FILES]) + (f" and {more} more" if more > 0 else "")
        lines.append(f"{head}: pattern {account['path']} matched {len(files)} file{_s(len(files))}: {shown}")
    grid = _grid(account)
    if account.get("inputs_from_spec"):
        lines.append(
            f"{head}: inputs {list(account.get('inputs', []))} read from the files' columns of those names (the "
            "model's inputs; data.control_columns not given)"
        )
    for f in files:
        lines.append(f"{head}: {_file_line(f, account, grid)}")
    return lines


def _s(n: int) -> str:
    return "" if n == 1 else "s"


def _grid(account: Mapping[str, Any]) -> str:
    parts = []
    if account.get("resample"):
        parts.append(f"resampled every {account['resample']:g} s")
    if int(account.get("stride") or 1) > 1:
        parts.append(f"every {account['stride']}th sample kept (data.stride)")
        if account.get("inputs") and account.get("input_hold") == "zoh":
            parts.append(
                f"the input{_s(len(account['inputs']))} averaged over each {account['stride']} samples (held zoh)"
            )
    return ", ".join(parts)


def _span(span: list[float], origin: float = 0.0) -> str:
    a, b = span[0] - origin, span[1] - origin
    return f"{a:.6g}–{b:.6g} s"


def _file_line(f: Mapping[str, Any], account: Mapping[str, Any], grid: str) -> str:
    name = Path(f["file"]).name
    origin = f["span"][0] if abs(f["span"][0]) >= 1e5 else 0.0  # a clock since 1970: from the first row
    since = " from its first row" if origin else ""
    rows = f"rows {f['range'][0]}–{f['range'][1] - 1}, " if "range" in f else ""
    head = f"{name}: {rows}{f['rows']} rows, {_span(f['span'], origin)}{since}"
    if f.get("time_origin"):
        head += f" (its times are ISO dates: seconds since {f['time_origin']})"
    texts = [head]
    for g in f.get("gaps", []):
        what = "filled by data.resample's interpolation" if g["action"] == "filled" else "splits it"
        texts.append(
            f"a gap of {g['seconds']:.4g} s ({g['steps']:.3g} steps) before row {g['row'] + 1} (t = "
            f"{g['t'] - origin:.6g} s) {what}"
        )
    texts += [clipped_text(c) for c in f.get("clipped", [])]
    if grid:
        texts.append(grid)
    pieces = f.get("pieces", [])
    for part in pieces:
        label = f"part {part['piece']} ({_span(part['span'], origin)}): " if len(pieces) > 1 else ""
        texts.append(label + _usage(part, account))
    return "; ".join(texts)


def _usage(part: Mapping[str, Any], account: Mapping[str, Any]) -> str:
    if part.get("skipped"):
        return f"not used ({part['skipped']})"
    samples = int(part.get("samples", part.get("rows", 0)))
    if "segments" not in part:
        return f"{samples} samples"
    count, used = int(part["segments"]), int(part.get("used", 0))
    seg = account.get("segment")
    if seg is None:
        return f"one trajectory of {samples} samples"
    if count == 0:
        return f"not used: its {samples} samples are shorter than one segment ({seg:g} s)"
    left = samples - used
    tail = f"; the last {left} are shorter than a segment, not used" if left else ""
    return f"{count} segment{_s(count)} of {seg:g} s use {used} of its {samples} samples{tail}"


def split_covers(splits: Any) -> dict[str, str]:
    """{split: what it covers} of data read from a file (each split's ``meta['covers']``): recordings' files and
    seconds ("ddp.csv 0–4 s"), or a batch file's trajectories by index ("3 of the file's 20 trajectories: 1, 4,
    9"). `splits`: a `mpsim.data.dataset.Splits`."""
    parts = (("train", splits.train), ("val", splits.val), ("test", splits.test))
    return {name: str(part.meta["covers"]) for name, part in parts if "covers" in part.meta}


def data_record(splits: Any) -> dict[str, Any]:
    """What `summary.json` and `diagnosis.json` keep of data read from a file: the account of its samples (for
    recordings) and what each split covers; empty for simulated data."""
    out: dict[str, Any] = {}
    covers = split_covers(splits)
    if covers:
        out["covers"] = covers
    accounts: list[Any] = []
    for part in (splits.train, splits.val, splits.test):  # one account, or one per part of a benchmark's split
        account = part.meta.get("account")
        if account is not None and account not in accounts:
            accounts.append(account)
    if accounts:
        out["accounts"] = accounts
    return out


def record_lines(record: Mapping[str, Any]) -> list[str]:
    """`data_record` as Markdown bullets (diagnosis.md's data section), without the "data: " prefix."""
    lines = [line for account in record.get("accounts", []) for line in account_lines(account)]
    lines += split_lines(record.get("covers", {}))
    return [f"- {line.removeprefix('data: ')}" for line in lines]


def split_lines(covers: Mapping[str, str]) -> list[str]:
    """What each split covers ({"train": "ddp.csv 0–4 s", ...}), one line for all: "data: train: ...; val: ..."."""
    parts = [f"{name}: {text}" for name, text in covers.items() if text]
    return [f"data: {'; '.join(parts)}"] if parts else []
