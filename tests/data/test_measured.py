"""Recordings as they come (`mpsim.data.measured`) and their place in the pipeline (`mpsim.data.pipeline`): wide
CSV files by a glob, columns mapped, a latent velocity estimated, segments split into contiguous blocks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mpsim.data.measured import Recordings, is_recording, paths_of, read_recordings
from mpsim.data.pipeline import DataOptions, load_splits
from mpsim.errors import ConfigError, DataError


def _wide(path: Path, t: np.ndarray, q: np.ndarray, u: np.ndarray, names=("time", "pos", "torque")) -> Path:
    rows = "\n".join(f"{a:.9f},{b:.9f},{c:.9f}" for a, b, c in zip(t, q, u, strict=True))
    path.write_text(",".join(names) + "\n" + rows + "\n")
    return path


def _sine(n: int, dt: float, omega: float = 2.0, t0: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = t0 + dt * np.arange(n)
    return t, np.sin(omega * t), np.cos(3 * t)


def test_a_long_csv_is_a_batch_and_a_wide_one_a_recording(tmp_path):
    long = tmp_path / "long.csv"
    long.write_text('"traj",t,node,x\n0,0,0,1\n0,1,0,2\n')
    wide = _wide(tmp_path / "wide.csv", *_sine(5, 0.1))
    assert not is_recording(long)
    assert is_recording(wide)
    assert is_recording(tmp_path / "x.mat")


def test_a_glob_reads_its_files_sorted_and_an_empty_one_is_refused(tmp_path):
    for name in ("b.csv", "a.csv", "c.txt"):
        (tmp_path / name).write_text("t,q\n0,1\n")
    assert [p.name for p in paths_of(tmp_path / "*.csv")] == ["a.csv", "b.csv"]
    with pytest.raises(DataError, match="matches no file"):
        paths_of(tmp_path / "*.mat")


def test_a_latent_velocity_is_estimated_from_positions(tmp_path):
    dt = 0.01
    t, q, u = _sine(501, dt)
    path = _wide(tmp_path / "r.csv", t, q, u)
    how = Recordings(
        time_column="time",
        columns={"q": "pos", "tau": "torque"},
        controls=["tau"],
        observed=["q"],
        states=["q", "v"],
        rates={"v": "q"},
    )
    batch = read_recordings(path, how)
    assert batch.state_names == ["q", "v"] and batch.control_names == ["tau"]
    v = batch.x[0, 5:-5, 0, 1].numpy()
    assert np.abs(v - 2 * np.cos(2 * t[5:-5])).max() < 1e-3  # the derivative of sin(2t), exact data
    assert batch.meta["observed"] == ["q"] and "v" in batch.meta["estimated"]


def test_a_latent_state_without_a_measured_rate_is_refused(tmp_path):
    path = _wide(tmp_path / "r.csv", *_sine(50, 0.01))
    how = Recordings(time_column="time", columns={"q": "pos"}, observed=["q"], states=["q", "w"], rates={})
    with pytest.raises(ConfigError, match=r"\['w'\].*cannot be estimated"):
        read_recordings(path, how)


def test_segments_split_into_contiguous_blocks_in_time_order(tmp_path):
    for k, rate in enumerate((0.01, 0.02)):  # two files of different rates, put on one grid
        t, q, u = _sine(int(4.0 / rate) + 1, rate, t0=10.0 * k)
        _wide(tmp_path / f"rec{k}.csv", t, q, u, names=("t", "q", "u"))
    options = DataOptions(
        path=str(tmp_path / "rec*.csv"), control_columns=["u"], resample=0.02, segment=1.0, split=[0.5, 0.25, 0.25]
    )
    splits = load_splits(options, tmp_path, "float64")
    assert [len(s) for s in (splits.train, splits.val, splits.test)] == [4, 2, 2]
    train_t0 = [e["t0"] for e in splits.train.meta["segments"]]
    test = splits.test.meta["segments"]
    assert train_t0 == [0.0, 1.0, 2.0, 3.0]
    assert all(e["recording"].endswith("rec1.csv") for e in test) and [e["t0"] for e in test] == [12.0, 13.0]
    assert splits.test.meta["covers"] == "rec1.csv 12–14 s"
    assert splits.train.meta["input_hold"] == "linear"


def test_recording_keys_are_refused_for_a_batch_file(tmp_path):
    long = tmp_path / "long.csv"
    long.write_text("traj,t,node,x\n0,0,0,1\n0,1,0,2\n")
    with pytest.raises(ConfigError, match="data.segment apply to recordings"):
        load_splits(DataOptions(path=str(long), segment=1.0), tmp_path, "float64")


def test_data_columns_must_be_a_mapping():
    with pytest.raises(ConfigError, match="data.columns must map"):
        DataOptions(columns=["q"]).recordings(None, {})  # type: ignore[arg-type]
