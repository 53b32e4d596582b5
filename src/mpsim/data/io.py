"""Reading and writing trajectories: `.npz` and long-format `.csv` (the formats users bring data in).

`.npz`: arrays ``t`` [T], ``x`` [B, T, N, D], optional ``u`` [B, T, N, C], ``edge_index`` [2, E] or
[B, 2, E] (padded with −1), ``node_features`` [N, F] or [B, N, F], and ``meta`` (a JSON string).

Long CSV: one row per (trajectory, time, node) with columns ``traj, t, node, <state names…>[, <control
names…>]``; the graph comes from an edge-list CSV with columns ``src, dst`` (optionally ``traj`` for one
graph per trajectory), by default ``<stem>_edges.csv`` beside the data. An optional sidecar
``<stem>.json`` holds the metadata. Bad files are refused with a message naming the file, the row or
column, and the fix.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from mpsim.data.table import TEXT_SUFFIXES, table_suffix
from mpsim.data.trajectories import Trajectories, grid_step
from mpsim.errors import DataError
from mpsim.files import atomic_write, json_default
from mpsim.safeload import META_BYTES, load_json, not_a_regular_file, parse_json

INDEX_COLUMNS = ("traj", "t", "node")


# ---- npz -----------------------------------------------------------------------------------------------
def save_npz(traj: Trajectories, path: str | Path) -> Path:
    """Write `traj` to `path` atomically (float64 states, JSON metadata)."""
    arrays: dict[str, Any] = {
        "t": traj.t.detach().double().cpu().numpy(),
        "x": traj.x.detach().double().cpu().numpy(),
        "edge_index": traj.edge_index.long().cpu().numpy(),
        "meta": np.array(json.dumps(traj.meta, default=json_default)),
    }
    if traj.u is not None:
        arrays["u"] = traj.u.detach().double().cpu().numpy()
    if traj.node_features is not None:
        arrays["node_features"] = traj.node_features.detach().double().cpu().numpy()
    return atomic_write(path, lambda f: np.savez(f, **arrays))


def load_npz(path: str | Path, edge_index: torch.Tensor | None = None) -> Trajectories:
    """Read an `.npz` written by `save_npz` or by hand (see the module docstring for the arrays)."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as err:  # noqa: BLE001
        raise DataError(f"{path}: cannot read as .npz ({type(err).__name__}: {err}).") from None
    missing = [k for k in ("t", "x") if k not in arrays]
    if missing:
        raise DataError(
            f"{path}: missing array(s) {missing}; found {sorted(arrays)}. An mpsim .npz needs t [T] and "
            "x [B, T, N, D] (see docs/data_formats.md)."
        )
    meta: dict[str, Any] = {}
    if "meta" in arrays:
        fix = "Keep only metadata there (names, dt, params; docs/data_formats.md)"
        try:
            meta = parse_json(str(arrays["meta"]), f"{path}: array 'meta'", fix, META_BYTES)
        except json.JSONDecodeError as err:
            raise DataError(f"{path}: array 'meta' is not valid JSON ({err}).") from None
        meta = check_meta(meta, f"{path}: array 'meta'")
    for key in ("t", "x", "u", "node_features"):
        if key in arrays:
            _check_real(arrays[key], key, path)
    if "edge_index" in arrays:
        ei = _integer_ids(arrays["edge_index"], path)
    elif edge_index is not None:
        ei = edge_index
    else:
        raise DataError(
            f"{path}: no 'edge_index' array and no graph given. Add edge_index [2, E] to the file, or pass "
            "data.edges=<edges.csv> or data.graph=system (with system=<name>)."
        )
    meta.setdefault("system", path.stem)
    meta["source"] = str(path)  # as for CSV: messages about the data name the file
    x = torch.from_numpy(arrays["x"]).double()
    t = torch.from_numpy(arrays["t"]).double()
    meta.setdefault("dt", grid_step(t))
    return _build(
        path,
        t=t,
        x=x,
        edge_index=ei,
        u=torch.from_numpy(arrays["u"]).double() if "u" in arrays else None,
        node_features=torch.from_numpy(arrays["node_features"]).double() if "node_features" in arrays else None,
        meta=meta,
    )


# ---- csv -----------------------------------------------------------------------------------------------
def save_csv(traj: Trajectories, path: str | Path) -> tuple[Path, Path]:
    """Write long-format `<path>`, its edge list `<stem>_edges.csv` and metadata `<stem>.json`."""
    path = Path(path)
    b, t_len, n, d = traj.x.shape
    grid = {
        "traj": np.repeat(np.arange(b), t_len * n),
        "t": np.tile(np.repeat(traj.t.detach().double().cpu().numpy(), n), b),
        "node": np.tile(np.arange(n), b * t_len),
    }
    for k, name in enumerate(traj.state_names):
        grid[name] = traj.x[..., k].double().cpu().numpy().reshape(-1)
    if traj.u is not None:
        for k, name in enumerate(traj.control_names):
            grid[name] = traj.u[..., k].double().cpu().numpy().reshape(-1)
    frame = pd.DataFrame(grid)
    atomic_write(path, lambda f: frame.to_csv(f, index=False, float_format="%.17g"), mode="w")
    ei = traj.edge_index.cpu()
    if ei.dim() == 2:
        edges = pd.DataFrame({"src": ei[0].numpy(), "dst": ei[1].numpy()})
    else:
        keep = ei[:, 0] >= 0
        traj_ids = torch.arange(b)[:, None].expand(-1, ei.shape[2])[keep]
        edges = pd.DataFrame({"traj": traj_ids.numpy(), "src": ei[:, 0][keep].numpy(), "dst": ei[:, 1][keep].numpy()})
    edge_path = path.with_name(f"{path.stem}_edges.csv")
    atomic_write(edge_path, lambda f: edges.to_csv(f, index=False), mode="w")
    meta = {**traj.meta, "control_columns": traj.control_names}
    atomic_write(path.with_suffix(".json"), lambda f: json.dump(meta, f, indent=1, default=json_default), mode="w")
    return path, edge_path


def load_csv(
    path: str | Path,
    edges: str | Path | None = None,
    edge_index: torch.Tensor | None = None,
    control_columns: list[str] | tuple[str, ...] = (),
) -> Trajectories:
    """Read a long-format CSV (see the module docstring).

    Args:
        path: the data file.
        edges: edge-list CSV (default: ``<stem>_edges.csv`` beside `path` if it exists).
        edge_index: [2, E] graph to use when there is no edge list (e.g. a system's graph).
        control_columns: columns that are controls rather than states (default: from the sidecar JSON).
    """
    path = Path(path)
    frame = _read_frame(path)
    meta = _read_sidecar(path.with_suffix(".json"))
    control_columns = list(control_columns) or list(meta.pop("control_columns", []) or [])
    value_cols, state_cols = _long_columns(frame, path, control_columns)
    numeric = {c: _numeric_column(frame, c, path) for c in ["t", "node", *value_cols]}
    node, n = _node_ids(numeric["node"], path)
    traj_codes, traj_labels = _traj_codes(frame, path)
    order, times = _long_grid(path, traj_codes, traj_labels, numeric["t"], node, n)
    b, t_len = len(traj_labels), len(times)
    x = np.stack([numeric[c][order] for c in state_cols], axis=-1).reshape(b, t_len, n, len(state_cols))
    u = None
    if control_columns:
        u = np.stack([numeric[c][order] for c in control_columns], axis=-1).reshape(b, t_len, n, len(control_columns))
    meta.update({"state_names": state_cols, "control_names": list(control_columns), "source": str(path)})
    meta.setdefault("system", path.stem)
    t = torch.from_numpy(times).double()
    meta.setdefault("dt", grid_step(t))
    return _build(
        path,
        t=t,
        x=torch.from_numpy(x).double(),
        edge_index=_csv_graph(path, edges, edge_index, n, traj_labels),
        u=None if u is None else torch.from_numpy(u).double(),
        node_features=None,
        meta=meta,
    )


def _read_frame(path: Path) -> pd.DataFrame:
    """The CSV at `path` as a table (one message for a missing, special or unparsable file)."""
    if not path.is_file():
        raise DataError(f"data file {path} {_not_a_file(path)}.")
    try:
        return pd.read_csv(path)
    except Exception as err:  # noqa: BLE001
        raise DataError(f"{path}: cannot parse as CSV ({type(err).__name__}: {err}).") from None


def _long_columns(frame: pd.DataFrame, path: Path, control_columns: list[str]) -> tuple[list[str], list[str]]:
    """A long CSV's value columns (all but traj, t, node) and, of those, the state columns (not controls)."""
    missing = [c for c in INDEX_COLUMNS if c not in frame.columns]
    if missing:
        raise DataError(
            f"{path}: missing column(s) {missing}; found {list(frame.columns)}. A long CSV needs columns "
            "traj, t, node followed by one column per state variable."
        )
    unknown_controls = [c for c in control_columns if c not in frame.columns]
    if unknown_controls:
        raise DataError(
            f"{path}: control column(s) {unknown_controls} not in the file's columns {list(frame.columns)}."
        )
    value_cols = [c for c in frame.columns if c not in INDEX_COLUMNS]
    state_cols = [c for c in value_cols if c not in control_columns]
    if not state_cols:
        raise DataError(f"{path}: no state columns besides traj, t, node.")
    if len(frame) == 0:
        raise DataError(f"{path}: the file has a header but no rows.")
    return value_cols, state_cols


def _node_ids(node: np.ndarray, path: Path) -> tuple[np.ndarray, int]:  # node: [rows] the 'node' column
    """The node column as integers, and the node count N (the ids must be 0..N-1, none missing)."""
    if not np.all(node == np.round(node)):
        row = int(np.nonzero(node != np.round(node))[0][0])
        raise DataError(f"{path}: row {row + 2}, column 'node': node ids must be integers; got {node[row]}.")
    node = node.astype(np.int64)
    node_ids = np.unique(node)
    n = int(node_ids.max()) + 1
    if node_ids.min() < 0 or len(node_ids) != n:
        raise DataError(
            f"{path}: column 'node' must hold the ids 0..N-1 with none missing; found {len(node_ids)} distinct "
            f"ids from {node_ids.min()} to {node_ids.max()}. Renumber the nodes from 0."
        )
    return node, n


def _traj_codes(frame: pd.DataFrame, path: Path) -> tuple[np.ndarray, Any]:
    """Each row's trajectory as a code 0..B-1, and the B labels in sorted order (no row may lack one)."""
    missing_traj = frame["traj"].isna().to_numpy()
    if missing_traj.any():
        row = int(np.nonzero(missing_traj)[0][0])
        raise DataError(
            f"{path}: row {row + 2}, column 'traj' is empty ({int(missing_traj.sum())} such rows). Every row needs the "
            "label of the trajectory it belongs to; fill it in or remove the row."
        )
    return pd.factorize(frame["traj"], sort=True)


def _long_grid(
    path: Path,
    traj_codes: np.ndarray,  # [rows] trajectory code of each row
    traj_labels: Any,
    t_vals: np.ndarray,  # [rows] time of each row
    node: np.ndarray,  # [rows] node id of each row
    n: int,
) -> tuple[np.ndarray, np.ndarray]:
    """The row order that lays the file out as [B, T, N], and the T shared times; refuses repeated rows and
    trajectories that do not share one full (time × node) grid."""
    b = len(traj_labels)
    key = pd.DataFrame({"traj": traj_codes, "t": t_vals, "node": node})
    dup = key.duplicated(keep=False).to_numpy()
    if dup.any():
        rows = (np.nonzero(dup)[0][:4] + 2).tolist()
        raise DataError(f"{path}: rows {rows} repeat the same (traj, t, node); each must appear once.")
    order = np.lexsort((node, t_vals, traj_codes))
    counts = np.bincount(traj_codes, minlength=b)
    times = np.unique(t_vals[traj_codes == 0])
    t_len = len(times)
    if len(t_vals) != b * t_len * n or np.any(counts != t_len * n):
        bad = int(np.nonzero(counts != t_len * n)[0][0]) if np.any(counts != t_len * n) else 0
        raise DataError(
            f"{path}: ragged data: trajectory {_label(traj_labels[bad])} has {counts[bad]} rows but a full grid needs "
            f"{t_len} times × {n} nodes = {t_len * n} (trajectory {_label(traj_labels[0])} has {t_len} time points). "
            "Every trajectory must have every node at the same times; resample or split the file."
        )
    grid_t = t_vals[order].reshape(b, t_len, n)
    if not np.allclose(grid_t, times[None, :, None], rtol=1e-9, atol=1e-12):
        bad = int(np.nonzero(~np.isclose(grid_t, times[None, :, None]).all(axis=(1, 2)))[0][0])
        raise DataError(
            f"{path}: ragged times: trajectory {_label(traj_labels[bad])} is not sampled at the same times as trajectory "
            f"{_label(traj_labels[0])} (or not at every node). All trajectories must share one time grid; subtract each "
            "trajectory's start time or resample."
        )
    return order, times


def _csv_graph(
    path: Path,
    edges: str | Path | None,
    edge_index: torch.Tensor | None,  # [2, E] a fallback graph, or None
    n: int,
    traj_labels: Any,
) -> torch.Tensor:
    """The graph of a long CSV: its edge list (given, or ``<stem>_edges.csv`` beside it), else `edge_index`, else
    none for one node; more nodes without a graph are refused."""
    edge_path = Path(edges) if edges else path.with_name(f"{path.stem}_edges.csv")
    if edges or edge_path.is_file():
        return load_edges(edge_path, n, traj_labels)
    if edge_index is not None:
        return edge_index
    if n == 1:  # one node has no neighbours: no edge list needed
        return torch.zeros(2, 0, dtype=torch.long)
    raise DataError(
        f"{path}: no graph: expected an edge list {edge_path.name} beside it. Pass data.edges=<edges.csv> "
        "(columns src,dst) or data.graph=system with system=<name>."
    )


def _not_a_file(path: Path) -> str:
    """Why `path` cannot be read as a file: nothing is there, or a folder, a named pipe, ... (never opened)."""
    return not_a_regular_file(path) or "is not a regular file"


def load_edges(path: str | Path, n_nodes: int, traj_labels: Any = None) -> torch.Tensor:
    """Edge list CSV (``src, dst`` [, ``traj``]) → [2, E] or [B, 2, E] padded with −1."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"edge list {path} {_not_a_file(path)}; pass data.edges=<path> (columns src,dst).")
    try:
        frame = pd.read_csv(path)
    except Exception as err:  # noqa: BLE001
        raise DataError(f"{path}: cannot parse as CSV ({type(err).__name__}: {err}).") from None
    missing = [c for c in ("src", "dst") if c not in frame.columns]
    if missing:
        raise DataError(f"{path}: missing column(s) {missing}; found {list(frame.columns)}. Use columns src,dst.")
    src, dst = (_numeric_column(frame, c, path) for c in ("src", "dst"))
    for name, col in (("src", src), ("dst", dst)):
        bad = np.nonzero((col != np.round(col)) | (col < 0) | (col >= n_nodes))[0]
        if len(bad):
            r = int(bad[0])
            raise DataError(
                f"{path}: row {r + 2}, column '{name}': node {col[r]:g} is outside the graph's nodes 0..{n_nodes - 1}."
            )
    ei = torch.from_numpy(np.stack([src, dst]).astype(np.int64))
    if "traj" not in frame.columns:
        return ei
    labels = list(traj_labels) if traj_labels is not None else sorted(frame["traj"].unique())
    lookup = {lab: i for i, lab in enumerate(labels)}
    unknown = [v for v in frame["traj"].unique() if v not in lookup]
    if unknown:
        shown = ", ".join(_label(v) for v in unknown[:4])
        raise DataError(f"{path}: column 'traj' names trajectories [{shown}] that are not in the data.")
    codes = np.array([lookup[v] for v in frame["traj"]])
    counts = np.bincount(codes, minlength=len(labels))
    e_max = int(counts.max()) if len(counts) else 0
    order = np.argsort(codes, kind="stable")
    slot = np.arange(len(codes)) - np.repeat(np.cumsum(counts) - counts, counts)
    out = torch.full((len(labels), 2, e_max), -1, dtype=torch.long)
    out[torch.from_numpy(codes[order]), :, torch.from_numpy(slot)] = ei[:, order].T
    return out


def load_trajectories(
    path: str | Path,
    edges: str | Path | None = None,
    edge_index: torch.Tensor | None = None,
    control_columns: list[str] | tuple[str, ...] = (),
) -> Trajectories:
    """Load `.npz` or `.csv` by extension."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"data file {path} {_not_a_file(path)} (data.path={path}).")
    if path.suffix == ".npz":
        ei = load_edges(edges, _npz_nodes(path)) if edges else edge_index
        return load_npz(path, ei)
    if table_suffix(path) in TEXT_SUFFIXES:
        return load_csv(path, edges, edge_index, control_columns)
    raise DataError(
        f"{path}: unknown data format {path.suffix!r}; mpsim reads .npz, .csv (also as .txt, .dat, .tsv, or any of "
        "them .gz) and MATLAB .mat files (docs/data_formats.md). Export the data to one of these."
    )


# ---- helpers -------------------------------------------------------------------------------------------
def _build(path: Path, **kwargs: Any) -> Trajectories:
    # the container's own checks, reported against the file
    x = kwargs["x"]
    if x.dim() == 4 and 0 in x.shape:
        axis = ["trajectories (B)", "time points (T)", "nodes (N)", "state variables (D)"][list(x.shape).index(0)]
        raise DataError(
            f"{path}: `x` has shape {tuple(x.shape)}: zero {axis}. The file holds no data to learn from; "
            "x must be [B, T, N, D] with every size >= 1."
        )
    try:
        return Trajectories(**kwargs)
    except DataError as err:
        msg = str(err)
        raise DataError(msg.replace("trajectories:", f"{path}:", 1)) from None


# keys of the metadata that mpsim reads, with the type each must have
META_TYPES: dict[str, tuple[type, ...]] = {
    "system": (str,),
    "state_names": (list,),
    "control_names": (list,),
    "control_columns": (list,),
    "node_feature_names": (list,),
    "dt": (int, float),
    "params": (dict,),
    "periods": (list,),
}
_JSON_TYPE_NAMES: dict[type, str] = {str: "string", list: "list", dict: "object"}


def check_meta(meta: Any, where: str) -> dict[str, Any]:
    """Metadata read from a file: a JSON object whose known keys (`META_TYPES`) have the right types.

    Raises:
        DataError: names the file (`where`), the key and the type expected.
    """
    if not isinstance(meta, dict):
        raise DataError(
            f'{where} must be a JSON object ({{"system": ..., "dt": ...}}); got a JSON '
            f"{type(meta).__name__}. Wrap the values in an object with named keys."
        )
    for key, kinds in META_TYPES.items():
        value = meta.get(key)
        if value is None:
            continue
        if not isinstance(value, kinds) or isinstance(value, bool):
            names = " or ".join("number" if k in (int, float) else _JSON_TYPE_NAMES[k] for k in kinds if k is not int)
            raise DataError(f"{where}: key '{key}' must be a {names}; got {json.dumps(value)[:80]}.")
        if (
            key in ("state_names", "control_names", "control_columns", "node_feature_names")
            and isinstance(value, list)
            and not all(isinstance(v, str) for v in value)
        ):
            raise DataError(f"{where}: key '{key}' must be a list of strings; got {json.dumps(value)[:80]}.")
        if key == "dt" and isinstance(value, (int, float)) and not (np.isfinite(value) and value > 0):
            raise DataError(f"{where}: key 'dt' must be a finite number > 0; got {value}.")
    return meta


def _read_sidecar(sidecar: Path) -> dict[str, Any]:
    """`<stem>.json` beside a CSV (its metadata), or {} without one."""
    if not sidecar.exists() or sidecar.is_dir():
        return {}
    fix = "Fix it, or delete it to load the CSV without metadata"
    try:
        meta = load_json(sidecar, META_BYTES, f"{sidecar}: the metadata file beside the CSV", fix)
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise DataError(f"{sidecar}: the metadata file beside the CSV is not valid JSON ({err}). {fix}.") from None
    return check_meta(meta, str(sidecar))


def _check_real(array: np.ndarray, key: str, path: Path) -> None:
    if np.iscomplexobj(array):
        raise DataError(
            f"{path}: array '{key}' is complex ({array.dtype}); mpsim needs real numbers. Store the real "
            "and imaginary parts as separate state variables."
        )
    if not np.issubdtype(array.dtype, np.number) or array.dtype == np.bool_:
        raise DataError(f"{path}: array '{key}' must be numeric; got dtype {array.dtype}.")


def _integer_ids(array: np.ndarray, path: Path) -> torch.Tensor:
    """`edge_index` as int64; float ids are accepted only when they are whole numbers (never truncated)."""
    array = np.asarray(array)
    if np.issubdtype(array.dtype, np.integer):
        return torch.from_numpy(array.astype(np.int64))
    _check_real(array, "edge_index", path)
    bad = ~np.isfinite(array) | (array != np.round(array))
    if bad.any():
        pos = tuple(int(i) for i in np.argwhere(bad)[0])
        raise DataError(
            f"{path}: array 'edge_index' holds node id {float(array[pos]):g} at {list(pos)}; node ids must be "
            "whole numbers. Save edge_index as an integer array (e.g. .astype(int)) with correct ids."
        )
    return torch.from_numpy(array.astype(np.int64))


def _label(value: Any) -> str:
    """A value from a file (a trajectory label, a cell) as the user wrote it: numpy scalars unwrapped, so a
    message shows `inf` or `'abc'`, not `np.float64(inf)`."""
    return repr(value.item() if hasattr(value, "item") else value)


def _numeric_column(frame: pd.DataFrame, col: str, path: Path) -> np.ndarray:
    values = pd.to_numeric(frame[col], errors="coerce").to_numpy(dtype=np.float64)
    bad = ~np.isfinite(values)
    if bad.any():
        row = int(np.nonzero(bad)[0][0])
        raw = frame[col].iloc[row]
        what = "is empty" if pd.isna(raw) else f"holds {_label(raw)}"  # inf, not np.float64(inf)
        raise DataError(
            f"{path}: row {row + 2}, column '{col}' {what} (not a finite number; {int(bad.sum())} such values in "
            "that column). Remove or interpolate those rows."
        )
    return values


def _npz_nodes(path: Path) -> int:
    with np.load(path, allow_pickle=False) as z:
        return int(z["x"].shape[2])
