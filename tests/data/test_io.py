import numpy as np
import pandas as pd
import pytest
import torch

from mpsim.data.io import load_csv, load_npz, load_trajectories, save_csv, save_npz
from mpsim.data.trajectories import Trajectories
from mpsim.errors import DataError
from mpsim.systems import CoupledPendulums


@pytest.fixture
def traj():
    return CoupledPendulums(n_nodes=3, graph="chain").generate(4, seed=0, horizon=6)


def test_npz_round_trip(traj, tmp_path):
    path = save_npz(traj, tmp_path / "d.npz")
    back = load_npz(path)
    assert torch.equal(back.x, traj.x) and torch.equal(back.t, traj.t)
    assert torch.equal(back.edge_index, traj.edge_index)
    assert back.meta["system"] == "pendulum2" and back.meta["state_names"] == ["theta", "omega"]
    assert not list(tmp_path.glob(".*tmp"))  # atomic write leaves no temporary file
    # messages about loaded data name the file it came from, as for CSV (not "data")
    assert back.meta["source"] == str(path) and load_csv(save_csv(traj, tmp_path / "d.csv")[0]).meta["source"]


def test_csv_round_trip_with_edge_list(traj, tmp_path):
    path, edges = save_csv(traj, tmp_path / "d.csv")
    assert edges.name == "d_edges.csv"
    back = load_csv(path)
    assert torch.allclose(back.x, traj.x, rtol=0, atol=1e-15)
    assert torch.equal(back.edge_index, traj.edge_index)
    assert back.state_names == ["theta", "omega"]


def _write(tmp_path, rows, columns=("traj", "t", "node", "theta", "omega"), edges=((0, 1), (1, 0))):
    path = tmp_path / "m.csv"
    pd.DataFrame(rows, columns=list(columns)).to_csv(path, index=False)
    pd.DataFrame(list(edges), columns=["src", "dst"]).to_csv(tmp_path / "m_edges.csv", index=False)
    return path


def _grid(n_traj=2, times=(0.0, 0.1, 0.2), nodes=2):
    return [[b, t, n, 0.1 * n + t, -t] for b in range(n_traj) for t in times for n in range(nodes)]


def test_hand_written_csv_loads(tmp_path):
    rows = _grid()
    rows.reverse()  # row order must not matter
    data = load_trajectories(_write(tmp_path, rows))
    assert data.x.shape == (2, 3, 2, 2)
    assert torch.allclose(data.x[1, 2, 1], torch.tensor([0.1 + 0.2, -0.2], dtype=torch.float64))
    assert data.meta["dt"] == pytest.approx(0.1)


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda r: r.__setitem__(3, [0, 0.1, 1, float("nan"), 0.0]), r"row 5, column 'theta' is empty"),
        (lambda r: r.__setitem__(2, [0, 0.1, 0, "abc", 0.0]), r"row 4, column 'theta' holds 'abc'"),
        (lambda r: r.__setitem__(4, [0, 0.2, 0, float("inf"), 0.0]), r"row 6, column 'theta'"),
        (lambda r: r.pop(5), r"ragged data: trajectory 0 has 5 rows"),
        (
            lambda r: r.__setitem__(6, [1, 0.15, 0, 0.0, 0.0]) or r.__setitem__(7, [1, 0.15, 1, 0.0, 0.0]),
            r"ragged times: trajectory 1",
        ),
        (lambda r: r.__setitem__(1, [0, 0.0, 0, 0.0, 0.0]), r"repeat the same \(traj, t, node\)"),
        (lambda r: [row.__setitem__(2, row[2] + 1) for row in r], r"ids 0..N-1"),
    ],
)
def test_bad_csv_is_refused_with_row_and_column(tmp_path, mutate, match):
    rows = _grid()
    mutate(rows)
    with pytest.raises(DataError, match=match) as err:
        load_trajectories(_write(tmp_path, rows))
    assert "m.csv" in str(err.value)


def test_missing_columns_are_named(tmp_path):
    path = _write(tmp_path, [[0, 0.0, 0.1]], columns=("traj", "time", "theta"))
    with pytest.raises(DataError, match=r"missing column\(s\) \['t', 'node'\]"):
        load_trajectories(path)


def test_edge_outside_the_graph_is_refused(tmp_path):
    path = _write(tmp_path, _grid(), edges=((0, 1), (1, 5)))
    with pytest.raises(DataError, match=r"m_edges.csv: row 3, column 'dst': node 5 is outside the graph's nodes 0..1"):
        load_trajectories(path)


def test_missing_graph_says_how_to_give_one(tmp_path):
    path = _write(tmp_path, _grid())
    (tmp_path / "m_edges.csv").unlink()
    with pytest.raises(DataError, match="data.edges"):
        load_trajectories(path)


def test_per_trajectory_edge_lists(tmp_path):
    rows = [[b, t, n, 0.0, 0.0] for b in ("a", "b") for t in (0.0, 1.0) for n in range(3)]
    path = tmp_path / "g.csv"
    pd.DataFrame(rows, columns=["traj", "t", "node", "theta", "omega"]).to_csv(path, index=False)
    pd.DataFrame([["a", 0, 1], ["b", 1, 2], ["b", 2, 1]], columns=["traj", "src", "dst"]).to_csv(
        tmp_path / "g_edges.csv", index=False
    )
    data = load_trajectories(path)
    assert data.edge_index.shape == (2, 2, 2)
    assert data.edge_index[0].tolist() == [[0, -1], [1, -1]]
    assert data.edge_index[1].tolist() == [[1, 2], [2, 1]]


def test_npz_without_x_or_with_bad_shape(tmp_path):
    np.savez(tmp_path / "a.npz", t=np.arange(3.0))
    with pytest.raises(DataError, match=r"missing array\(s\) \['x'\]"):
        load_trajectories(tmp_path / "a.npz")
    np.savez(tmp_path / "b.npz", t=np.arange(3.0), x=np.zeros((3, 2, 2)), edge_index=np.zeros((2, 0), int))
    with pytest.raises(DataError, match=r"b.npz: `x` must be \[B, T, N, D\]"):
        load_trajectories(tmp_path / "b.npz")


def test_unknown_extension(tmp_path):
    (tmp_path / "d.xlsx").write_text("x")
    with pytest.raises(DataError, match=r"unknown data format '.xlsx'; mpsim reads .npz, .csv"):
        load_trajectories(tmp_path / "d.xlsx")


def test_a_long_csv_named_txt_or_gzipped_reads_as_the_csv(tmp_path):
    import gzip
    import shutil

    text = "traj,t,node,x\n0,0,0,1\n0,1,0,2\n1,0,0,3\n1,1,0,4\n"
    (tmp_path / "d.csv").write_text(text)
    (tmp_path / "d.txt").write_text(text)
    with open(tmp_path / "d.csv", "rb") as src, gzip.open(tmp_path / "d.csv.gz", "wb") as dst:
        shutil.copyfileobj(src, dst)
    want = load_trajectories(tmp_path / "d.csv").x
    for name in ("d.txt", "d.csv.gz"):
        assert torch.equal(load_trajectories(tmp_path / name).x, want)


def test_a_folder_given_as_a_data_file_or_edge_list_is_named_as_one(tmp_path, traj):
    (tmp_path / "runs.csv").mkdir()
    for path in (tmp_path, tmp_path / "runs.csv"):
        with pytest.raises(DataError, match="is a folder, not a file"):
            load_trajectories(path)
    csv_path, _ = save_csv(traj, tmp_path / "d.csv")
    with pytest.raises(DataError, match=r"edge list .* is a folder, not a file; pass data.edges"):
        load_trajectories(csv_path, edges=tmp_path)
    with pytest.raises(DataError, match="does not exist"):
        load_trajectories(tmp_path / "none.npz")


def test_container_checks_time_grid():
    with pytest.raises(DataError, match="strictly increasing"):
        Trajectories(t=torch.tensor([0.0, 1.0, 1.0]), x=torch.zeros(1, 3, 1, 1), edge_index=torch.zeros(2, 0).long())


def test_concat_refuses_to_drop_controls():
    grid, ei = torch.tensor([0.0, 1.0]), torch.zeros(2, 0).long()
    with_u = Trajectories(t=grid, x=torch.zeros(1, 2, 1, 1), edge_index=ei, u=torch.zeros(1, 2, 1, 1))
    without_u = Trajectories(t=grid, x=torch.zeros(1, 2, 1, 1), edge_index=ei)
    assert Trajectories.concat([with_u, with_u]).u.shape == (2, 2, 1, 1)
    with pytest.raises(DataError, match="without"):
        Trajectories.concat([with_u, without_u])


def test_empty_traj_cell_is_named(tmp_path):
    rows = _grid()
    rows[3][0] = None
    with pytest.raises(DataError, match=r"m.csv: row 5, column 'traj' is empty \(1 such rows\)"):
        load_trajectories(_write(tmp_path, rows))


@pytest.mark.parametrize(
    "text, match",
    [
        ("{oops", r"m.json: the metadata file beside the CSV is not valid JSON"),
        ('["a"]', r"m.json must be a JSON object .* got a JSON list"),
        ('{"dt": "fast"}', r"m.json: key 'dt' must be a number"),
        ('{"control_columns": [1]}', r"key 'control_columns' must be a list of strings"),
    ],
)
def test_bad_sidecar_json_is_named(tmp_path, text, match):
    path = _write(tmp_path, _grid())
    (tmp_path / "m.json").write_text(text)
    with pytest.raises(DataError, match=match):
        load_trajectories(path)


def _npz(tmp_path, **arrays):
    base = {"t": np.arange(3.0), "x": np.zeros((2, 3, 2, 1)), "edge_index": np.array([[0, 1], [1, 0]])}
    np.savez(tmp_path / "a.npz", **{**base, **arrays})
    return tmp_path / "a.npz"


def test_npz_values_are_never_cast_silently(tmp_path):
    with pytest.raises(DataError, match="array 'meta' must be a JSON object"):
        load_trajectories(_npz(tmp_path, meta=np.array("[1]")))
    with pytest.raises(DataError, match=r"node id 0.5 at \[1, 1\]"):
        load_trajectories(_npz(tmp_path, edge_index=np.array([[0.0, 1.0], [1.0, 0.5]])))
    assert load_trajectories(_npz(tmp_path, edge_index=np.array([[0.0, 1.0], [1.0, 0.0]]))).edge_index.tolist() == [
        [0, 1],
        [1, 0],
    ]
    with pytest.raises(DataError, match="array 'x' is complex"):
        load_trajectories(_npz(tmp_path, x=np.zeros((2, 3, 2, 1), dtype=complex)))
    with pytest.raises(DataError, match=r"zero nodes \(N\)"):
        load_trajectories(_npz(tmp_path, x=np.zeros((2, 3, 0, 1)), edge_index=np.zeros((2, 0), dtype=int)))


def test_values_beyond_the_model_precision_are_reported_as_overflow(tmp_path):
    from mpsim.data.precision import check_representable

    data = load_trajectories(_npz(tmp_path, x=np.full((2, 3, 2, 1), 1e300)))
    with pytest.raises(DataError, match=r"x\[0, 0, 0, 0\] = 1e\+300: values this large overflow float32"):
        check_representable(data, "float32", "a.npz")
    with pytest.raises(DataError, match="overflow float64 when squared"):
        check_representable(data, "float64", "a.npz")
    check_representable(load_trajectories(_npz(tmp_path, x=np.full((2, 3, 2, 1), 1e30))), "float32", "a.npz")


def test_times_beyond_the_model_precision_are_named_with_their_range(tmp_path):
    from mpsim.data.precision import check_representable

    huge = load_trajectories(_npz(tmp_path, t=np.array([0.0, 2.5e300, 5e300])))  # finite: not "NaN or inf"
    with pytest.raises(DataError, match=r"a.npz: `t` runs from 0.0 to 5e\+300: values this large overflow float32"):
        check_representable(huge, "float32", "a.npz")
    check_representable(huge, "float64", "a.npz")
    close = load_trajectories(_npz(tmp_path, t=1e10 + np.array([0.0, 0.01, 0.02])))
    with pytest.raises(DataError, match=r"t\[0\] = 10000000000.0 and t\[1\] = 10000000000.01 are the same number"):
        check_representable(close, "float32", "a.npz")
    check_representable(close, "float64", "a.npz")
    spread = load_trajectories(_npz(tmp_path, t=np.array([-1e308, 1e308, 1.5e308])))
    with pytest.raises(DataError, match="the steps between time points overflow float64"):
        check_representable(spread, "float64", "a.npz")


def test_a_nan_time_is_named_with_its_index(tmp_path):
    with pytest.raises(DataError, match=r"a.npz: `t` holds nan at index 1"):
        load_trajectories(_npz(tmp_path, t=np.array([0.0, np.nan, 2.0])))


def test_messages_show_plain_numbers_not_numpy_reprs(tmp_path):
    rows = _grid()
    rows[2][3] = float("inf")
    with pytest.raises(DataError, match=r"row 4, column 'theta' holds inf \(not a finite number") as err:
        load_trajectories(_write(tmp_path, rows))
    assert "np." not in str(err.value)
    path = _write(tmp_path, _grid())
    pd.DataFrame([[7, 0, 1]], columns=["traj", "src", "dst"]).to_csv(tmp_path / "m_edges.csv", index=False)
    with pytest.raises(DataError, match=r"names trajectories \[7\] that are not in the data"):
        load_trajectories(path)


def test_deep_or_oversized_metadata_is_refused_before_it_is_parsed(tmp_path, monkeypatch):
    from mpsim.data import io

    with pytest.raises(DataError, match="array 'meta' nests lists or objects 100,000 levels deep"):
        load_trajectories(_npz(tmp_path, meta=np.array("[" * 100_000 + "]" * 100_000)))
    path = _write(tmp_path, _grid())
    (tmp_path / "m.json").write_text('{"a": ' * 1000 + "1" + "}" * 1000)
    with pytest.raises(DataError, match="m.json: the metadata file beside the CSV nests lists or objects 1,000 levels"):
        load_trajectories(path)
    (tmp_path / "m.json").write_text('{"system": "' + "s" * 2000 + '"}')
    monkeypatch.setattr(io, "META_BYTES", 1000)
    with pytest.raises(
        DataError, match="m.json: the metadata file beside the CSV is 1.97 kB, over mpsim's limit of 0.977 kB"
    ):
        load_trajectories(path)


def test_a_named_pipe_is_refused_without_blocking(tmp_path):
    import os

    os.mkfifo(tmp_path / "p.npz")
    with pytest.raises(DataError, match="p.npz is a named pipe \\(FIFO\\), not a regular file"):
        load_trajectories(tmp_path / "p.npz")
    path = _write(tmp_path, _grid())
    os.mkfifo(tmp_path / "m.json")
    with pytest.raises(DataError, match="m.json: the metadata file beside the CSV is a named pipe"):
        load_trajectories(path)


def test_one_node_csv_needs_no_edge_list(tmp_path):
    rows = [
        {"traj": r, "t": 0.1 * k, "node": 0, "theta": 0.1 * k + r, "omega": 1.0} for r in range(2) for k in range(5)
    ]
    pd.DataFrame(rows).to_csv(tmp_path / "one.csv", index=False)
    data = load_trajectories(tmp_path / "one.csv")
    assert data.x.shape == (2, 5, 1, 2) and data.edge_index.shape == (2, 0)
    rows = [{**r, "node": n} for r in rows for n in (0, 1)]  # two nodes and no edge list: still refused
    pd.DataFrame(rows).to_csv(tmp_path / "two.csv", index=False)
    with pytest.raises(DataError, match="no graph"):
        load_trajectories(tmp_path / "two.csv")
