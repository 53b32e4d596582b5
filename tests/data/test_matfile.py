"""MATLAB files (`mpsim.data.matfile.read_mat`): v5 written with scipy, v7.3 (HDF5) with h5py when installed."""

import numpy as np
import pytest
from scipy.io import savemat

from mpsim.data.matfile import read_mat
from mpsim.data.recording import to_recording
from mpsim.errors import DataError

T = 50


@pytest.fixture
def signals():
    rng = np.random.default_rng(1)
    t = np.arange(T) * 0.01
    return {"t": t, "q": np.sin(t), "v": np.cos(t), "u": rng.standard_normal(T), "m": rng.standard_normal((T, 2))}


@pytest.fixture
def v5(tmp_path, signals):
    path = tmp_path / "rec.mat"
    cell = np.empty((1, 2), dtype=object)
    cell[0, 0], cell[0, 1] = np.ones(3), "text"
    savemat(
        path,
        {
            "t": signals["t"][:, None],  # N×1
            "q": signals["q"][None, :],  # 1×N
            "u": signals["u"].astype(np.float32),
            "m": signals["m"].T,  # 2×N: one signal per row
            "s": {"v": signals["v"], "inner": {"k": np.arange(T, dtype=np.int16)}},
            "short": np.arange(7.0),
            "c": cell,
            "name": "rig 3",
            "fs": 100.0,
            "z": np.ones((T, 2, 2)),
        },
    )
    return path


def test_v5_variables_become_columns(v5, signals):
    table = read_mat(v5)
    assert table.time_column == "t" and np.array_equal(table.t, signals["t"])
    assert np.array_equal(table.columns["q"], signals["q"])
    assert np.allclose(table.columns["u"], signals["u"].astype(np.float32))
    assert np.array_equal(table.columns["m.1"], signals["m"][:, 0]) and np.array_equal(
        table.columns["m.2"], signals["m"][:, 1]
    )
    assert np.array_equal(table.columns["s.v"], signals["v"]) and table.columns["s.inner.k"][-1] == T - 1
    assert "cell array" in table.unusable["c"] and table.unusable["name"] == "text"
    assert table.unusable["fs"] == "a single number, not a signal" and "50×2×2 array" in table.unusable["z"]


def test_v5_mapping_struct_fields_and_matrix_columns(v5, signals):
    rec = to_recording(read_mat(v5), {"v": "s.v", "w": "m.2"}, ["q", "v", "w"], ["u"])
    assert rec.x.shape == (1, T, 1, 3) and rec.u.shape == (1, T, 1, 1)
    assert np.array_equal(rec.x[0, :, 0, 2].numpy(), signals["m"][:, 1])


def test_unusable_and_short_variables_are_named_when_mapped(v5):
    table = read_mat(v5)
    with pytest.raises(DataError, match=r"'q' \(mapped to column 'c' by data.columns\) cannot be used: it is a cell"):
        to_recording(table, {"q": "c"}, ["q"])
    with pytest.raises(DataError, match=r"column 'short' \(for 'q'\) has 7 samples but the time column 't' has 50"):
        to_recording(table, {"q": "short"}, ["q"])


def test_without_time_variable_dt_gives_the_times_from_the_columns_picked(tmp_path):
    path = tmp_path / "no_t.mat"
    savemat(path, {"q": np.arange(5.0), "other": np.arange(9.0)})
    rec = to_recording(read_mat(path, dt=0.5), None, ["q"])
    assert rec.t.tolist() == [0.0, 0.5, 1.0, 1.5, 2.0]
    with pytest.raises(DataError, match="different lengths .* no time column"):
        to_recording(read_mat(path, dt=0.5), {"v": "other"}, ["q", "v"])
    with pytest.raises(DataError, match="no time column 't'.*data.dt"):
        read_mat(path)


def test_struct_arrays_and_foreign_files_are_refused(tmp_path):
    path = tmp_path / "sa.mat"
    savemat(path, {"t": np.arange(3.0), "sa": np.array([(1.0,), (2.0,)], dtype=[("a", object)])})
    assert "struct array" in read_mat(path).unusable["sa"]
    junk = tmp_path / "junk.mat"
    junk.write_bytes(b"not a mat file at all" * 10)
    with pytest.raises(DataError, match="not a MATLAB .mat file"):
        read_mat(junk)
    with pytest.raises(DataError, match="does not exist"):
        read_mat(tmp_path / "none.mat")


def _write_v73(path, signals, h5py):
    """A file laid out as MATLAB's save -v7.3 does: a 512-byte header, arrays stored transposed, class attributes."""
    with h5py.File(path, "w", userblock_size=512) as f:
        for name, value in (("t", signals["t"][None, :]), ("q", signals["q"][None, :]), ("m", signals["m"].T)):
            f.create_dataset(name, data=value).attrs["MATLAB_class"] = np.bytes_("double")
        group = f.create_group("s")
        group.attrs["MATLAB_class"] = np.bytes_("struct")
        group.create_dataset("v", data=signals["v"][None, :]).attrs["MATLAB_class"] = np.bytes_("double")
        f.create_dataset("name", data=np.frombuffer(b"rig", dtype=np.uint8)[:, None].astype(np.uint16)).attrs[
            "MATLAB_class"
        ] = np.bytes_("char")
        refs = f.create_dataset("c", (1, 2), dtype=h5py.ref_dtype)
        refs.attrs["MATLAB_class"] = np.bytes_("cell")
    header = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 00:00:00 2026 HDF5 schema 1.00 ."
    with open(path, "r+b") as f:
        f.write(header.ljust(116) + b"\0" * 8 + b"\x00\x02" + b"IM")


def test_v73_hdf5_is_read_through_h5py(tmp_path, signals):
    h5py = pytest.importorskip("h5py")
    path = tmp_path / "rec73.mat"
    _write_v73(path, signals, h5py)
    table = read_mat(path)
    assert np.array_equal(table.t, signals["t"]) and np.array_equal(table.columns["q"], signals["q"])
    assert np.array_equal(table.columns["m.2"], signals["m"][:, 1]) and np.array_equal(
        table.columns["s.v"], signals["v"]
    )
    assert table.unusable["name"] == "text" and "cell array" in table.unusable["c"]


def test_v73_without_h5py_says_what_to_install(tmp_path, monkeypatch):
    path = tmp_path / "rec73.mat"
    header = b"MATLAB 7.3 MAT-file".ljust(116) + b"\0" * 8 + b"\x00\x02" + b"IM"
    path.write_bytes(header + b"\0" * 512)
    monkeypatch.setitem(__import__("sys").modules, "h5py", None)  # import h5py raises ImportError
    with pytest.raises(DataError, match=r"v7.3 file \(HDF5\), which needs the h5py package: pip install h5py"):
        read_mat(path)
