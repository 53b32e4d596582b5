"""Compare two runs' outputs file by file: `python compare.py KIND BEFORE AFTER` prints one table row.

KIND is csv (metrics.csv, byte-identical once the wall-time columns are dropped), ckpt (every tensor equal with
torch.equal), json (every number equal), npz (every array equal, and the bytes) or bytes. Exit 0 if they match.
Imports torch and numpy only (nothing of mpsim).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

WALL_COLUMNS = ("epoch_time", "wall_time")  # metrics.csv: seconds measured, not computed
# summary.json / diagnosis.json keys that hold a time, a path or a run's place, not a computed number
NOT_NUMBERS = ("time", "wall", "run_dir", "path", "checkpoint")


def _csv(a: Path, b: Path) -> tuple[bool, str]:
    def kept(path: Path) -> tuple[list[str], str]:
        rows = [line.split(",") for line in path.read_text().splitlines()]
        cols = [i for i, name in enumerate(rows[0]) if name not in WALL_COLUMNS]
        return rows[0], "\n".join(",".join(r[i] for i in cols) for r in rows)

    (head_a, text_a), (head_b, text_b) = kept(a), kept(b)
    dropped = [c for c in head_a if c in WALL_COLUMNS]
    same = text_a == text_b and head_a == head_b
    return same, f"{len(text_a.splitlines()) - 1} rows x {len(head_a) - len(dropped)} columns (dropped {dropped})"


def _leaves(obj, prefix=""):
    """(dotted key, value) of every leaf of nested dicts and lists."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _leaves(v, f"{prefix}.{k}" if prefix else str(k))
    elif isinstance(obj, list | tuple):
        for i, v in enumerate(obj):
            yield from _leaves(v, f"{prefix}[{i}]")
    else:
        yield prefix, obj


def _ckpt(a: Path, b: Path) -> tuple[bool, str]:
    import torch

    ca, cb = (torch.load(p, map_location="cpu", weights_only=False) for p in (a, b))
    ta = {k: v for k, v in _leaves(ca) if isinstance(v, torch.Tensor)}
    tb = {k: v for k, v in _leaves(cb) if isinstance(v, torch.Tensor)}
    sd = [k for k in ta if ".state_dict." in k]
    bad = [k for k in ta if k not in tb or ta[k].shape != tb[k].shape or not torch.equal(ta[k], tb[k])]
    bad += [f"{k} (after only)" for k in tb if k not in ta]
    return not bad, f"{len(ta)} tensors ({len(sd)} in state_dict) torch.equal" + (f"; differ: {bad}" if bad else "")


def _numbers(path: Path) -> dict[str, float]:
    leaves = _leaves(json.loads(path.read_text()))
    return {
        k: v
        for k, v in leaves
        if isinstance(v, int | float) and not isinstance(v, bool) and not any(w in k.lower() for w in NOT_NUMBERS)
    }


def _json(a: Path, b: Path) -> tuple[bool, str]:
    na, nb = _numbers(a), _numbers(b)
    common = sorted(set(na) & set(nb))
    bad = [f"{k}: {na[k]!r} -> {nb[k]!r}" for k in common if na[k] != nb[k] and not (na[k] != na[k] and nb[k] != nb[k])]
    note = f"{len(common)} numbers equal" if not bad else f"{len(bad)} of {len(common)} numbers differ: {bad}"
    for side, keys in (("before", set(na) - set(nb)), ("after", set(nb) - set(na))):
        if keys:
            note += f"; {side} only: {sorted(keys)}"
    return not bad, note


def _npz(a: Path, b: Path) -> tuple[bool, str]:
    import numpy as np

    za, zb = np.load(a), np.load(b)

    def equal(x, y) -> bool:
        return x.dtype == y.dtype and np.array_equal(x, y, equal_nan=x.dtype.kind in "fc")

    bad = [k for k in za.files if k not in zb.files or not equal(za[k], zb[k])]
    bad += [k for k in zb.files if k not in za.files]
    same_bytes = a.read_bytes() == b.read_bytes()
    note = f"{len(za.files)} arrays equal ({', '.join(za.files)}); bytes {'identical' if same_bytes else 'differ'}"
    return not bad, note if not bad else f"arrays differ: {bad}"


def _bytes(a: Path, b: Path) -> tuple[bool, str]:
    same = a.read_bytes() == b.read_bytes()
    return same, f"{a.stat().st_size} bytes {'identical' if same else 'differ'}"


def main(kind: str, a: str, b: str) -> int:
    pa, pb = Path(a), Path(b)
    if not pa.exists() or not pb.exists():
        print(f"MISSING: {' '.join(str(p) for p in (pa, pb) if not p.exists())}")
        return 1
    same, note = {"csv": _csv, "ckpt": _ckpt, "json": _json, "npz": _npz, "bytes": _bytes}[kind](pa, pb)
    print(f"{'same' if same else 'DIFFERENT'}: {note}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
