"""MATLAB `.mat` files: one measured recording per file, one variable per signal.

Versions 4, 5 and 7 are read with `scipy.io.loadmat`; version 7.3 (an HDF5 file) with h5py, if it is installed
(``pip install h5py``, or the extra ``pip install 'mpsim[hdf5]'``). How variables become columns:

- a vector (N×1 or 1×N, any numeric or logical class) is the column of its name;
- a matrix of several signals is split along its shorter axis (the longer one is time; a square matrix is read
  as one signal per column): ``data.1``, ``data.2``, ... are MATLAB's ``data(:,1)``, ``data(:,2)``, ... (1-based,
  and writable in an override without quotes: ``data.columns={q: data.1}``);
- a struct's fields are ``struct.field`` (nested structs ``a.b.c``);
- anything else is set aside and named if a model asks for it: cell arrays, text, complex numbers, struct arrays,
  sparse matrices, arrays of three or more dimensions, scalars and empty arrays. Nothing is unpickled or executed:
  cell and object arrays are refused, never read.

Variables may differ in length: only those with the time column's length (`data.time_column`, default ``t``) are
usable with it, and a mapped variable of another length is refused with both lengths named. Without a time
variable, `data.dt` gives t = k·dt.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from mpsim.data.table import DATA_BYTES, Table, time_grid
from mpsim.errors import DataError
from mpsim.safeload import not_a_regular_file, size_text

_CELL = "a cell array (mpsim reads numeric arrays only; store each signal as a numeric vector, e.g. cell2mat)"


def read_mat(path: str | Path, time_column: str | None = "t", dt: float | None = None) -> Table:
    """The columns of the MATLAB file `path` (see the module docstring).

    Args:
        path: the `.mat` file.
        time_column: `data.time_column`, the variable holding the times (None: the file has none, use `dt`).
        dt: `data.dt`, the sampling step in seconds for a file without a time variable.

    Raises:
        DataError: not a regular file, over `DATA_BYTES`, not a MAT-file, a v7.3 file without h5py, no numeric
            variable, or a time variable that is missing, not finite or not increasing.
    """
    path = Path(path)
    why = not_a_regular_file(path)
    if why is not None:
        raise DataError(f"data file {path} {why} (data.path={path}).")
    size = os.stat(path).st_size
    if size > DATA_BYTES:
        raise DataError(
            f"data file {path} is {size_text(size)}, over mpsim's limit of {size_text(DATA_BYTES)}. Split the "
            "recording into several files (data.path takes a glob) or decimate it."
        )
    columns: dict[str, np.ndarray] = {}
    unusable: dict[str, str] = {}
    if _version(path) == 2:
        _read_hdf5(path, columns, unusable)
    else:
        _read_v5(path, columns, unusable)
    if not columns:
        shown = f"; set aside: {unusable}" if unusable else ""
        raise DataError(f"{path}: no numeric vector or matrix variable in the file{shown}.")
    where = _sample
    t, used = time_grid(columns, time_column, dt, str(path), where)
    return Table(t=t, columns=columns, source=str(path), dt=None if used else dt, time_column=used,
                 unusable=unusable, where=where)  # fmt: skip


def _sample(i: int) -> str:
    return f"sample {i + 1}"


def _version(path: Path) -> int:
    """The MAT-file's major version: 0 (v4), 1 (v5/v7) or 2 (v7.3, HDF5)."""
    from scipy.io.matlab import matfile_version

    try:
        return int(matfile_version(str(path))[0])
    except Exception as err:  # noqa: BLE001 (scipy raises ValueError, TypeError, OSError for a foreign file)
        raise DataError(
            f"{path}: not a MATLAB .mat file ({err}). Save it from MATLAB with save(..., '-v7') or '-v7.3', or "
            "export a CSV (docs/data_formats.md, 'Measured recordings')."
        ) from None


def _read_v5(path: Path, columns: dict[str, np.ndarray], unusable: dict[str, str]) -> None:
    from scipy.io import loadmat

    try:
        variables = loadmat(str(path), squeeze_me=False, struct_as_record=True, chars_as_strings=True)
    except Exception as err:  # noqa: BLE001 (a damaged file raises many kinds)
        raise DataError(f"{path}: cannot read as a MAT-file ({type(err).__name__}: {err}).") from None
    for name, value in variables.items():
        if not name.startswith("__"):  # __header__, __version__, __globals__
            _add_v5(name, value, columns, unusable)


def _add_v5(name: str, value: Any, columns: dict[str, np.ndarray], unusable: dict[str, str]) -> None:
    """Flatten one variable read by loadmat into `columns` (or say in `unusable` why not)."""
    if not isinstance(value, np.ndarray):
        unusable[name] = f"a {type(value).__name__} (a sparse matrix or another non-array value)"
    elif value.dtype.names:
        if value.size != 1:
            unusable[name] = f"a {'×'.join(map(str, value.shape))} struct array (mpsim reads single structs)"
            return
        for field in value.dtype.names:
            _add_v5(f"{name}.{field}", value[field].flat[0], columns, unusable)
    elif value.dtype == object:
        unusable[name] = _CELL
    else:
        _add_numeric(name, value, columns, unusable)


def _add_numeric(name: str, value: np.ndarray, columns: dict[str, np.ndarray], unusable: dict[str, str]) -> None:
    """A numeric array as one column (a vector) or one per signal (`name.1`, ... for a matrix)."""
    kind = value.dtype.kind
    if kind in "US":
        unusable[name] = "text"
        return
    if kind == "c":
        unusable[name] = "complex numbers (store the real and imaginary parts as separate variables)"
        return
    if kind not in "biuf":
        unusable[name] = f"of MATLAB/numpy type {value.dtype}, not numbers"
        return
    shape = [s for s in value.shape if s != 1]
    if value.size == 0 or not shape:
        unusable[name] = "empty" if value.size == 0 else "a single number, not a signal"
        return
    if len(shape) > 2:
        unusable[name] = f"a {'×'.join(map(str, value.shape))} array (mpsim reads vectors and matrices)"
        return
    if len(shape) == 1:
        columns[name] = value.reshape(-1).astype(np.float64)
        return
    matrix = value.reshape(shape)
    if matrix.shape[1] > matrix.shape[0]:
        matrix = matrix.T  # the longer axis is time
    for k in range(matrix.shape[1]):  # a loop over the few signals of the matrix
        columns[f"{name}.{k + 1}"] = matrix[:, k].astype(np.float64)


def _read_hdf5(path: Path, columns: dict[str, np.ndarray], unusable: dict[str, str]) -> None:
    """A v7.3 MAT-file through h5py (MATLAB writes arrays transposed: column-major)."""
    try:
        import h5py  # type: ignore[import-not-found, import-untyped, unused-ignore]
    except ImportError:
        raise DataError(
            f"{path}: a MATLAB v7.3 file (HDF5), which needs the h5py package: pip install h5py. Or save it from "
            "MATLAB with save(..., '-v7')."
        ) from None
    try:
        with h5py.File(path, "r") as handle:
            for name, node in handle.items():
                if not name.startswith("#"):  # #refs#, #subsystem#: MATLAB's internal groups
                    _add_hdf5(name, node, columns, unusable, h5py)
    except OSError as err:
        raise DataError(f"{path}: cannot read as a MATLAB v7.3 (HDF5) file ({err}).") from None


def _add_hdf5(name: str, node: Any, columns: dict[str, np.ndarray], unusable: dict[str, str], h5py: Any) -> None:
    matlab_class = node.attrs.get("MATLAB_class", b"")
    matlab_class = matlab_class.decode() if isinstance(matlab_class, bytes) else str(matlab_class)
    if isinstance(node, h5py.Group):
        if matlab_class not in ("struct", ""):
            unusable[name] = f"a MATLAB {matlab_class} object (mpsim reads numeric arrays and structs)"
            return
        for field, child in node.items():
            _add_hdf5(f"{name}.{field}", child, columns, unusable, h5py)
        return
    if matlab_class == "cell" or node.dtype.kind == "O" or h5py.check_dtype(ref=node.dtype) is not None:
        unusable[name] = _CELL
    elif matlab_class == "char":
        unusable[name] = "text"
    elif node.attrs.get("MATLAB_empty", 0):
        unusable[name] = "empty"
    elif node.dtype.names:  # MATLAB stores complex numbers as a compound of real and imag
        unusable[name] = "complex numbers (store the real and imaginary parts as separate variables)"
    else:
        _add_numeric(name, np.asarray(node[()]).T, columns, unusable)
