"""Recordings as they come (`mpsim.data.measured`) and their place in the pipeline (`mpsim.data.pipeline`): wide
CSV files by a glob, columns mapped, a latent velocity estimated, segments split into contiguous blocks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mpsim.data.account import account_lines
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


def test_a_latent_state_no_measured_state_is_the_rate_of_is_left_to_the_model(tmp_path):
    path = _wide(tmp_path / "r.csv", *_sine(50, 0.01))
    how = Recordings(time_column="time", columns={"q": "pos"}, observed=["q"], states=["q", "w"], rates={})
    batch = read_recordings(path, how)
    assert batch.meta["pending"] == ["w"] and float(batch.x[..., 1].abs().max()) == 0.0
    assert batch.meta["estimated"]["w"] == "pending: the model-based estimate"


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


def _opts(path: Path, **keys) -> DataOptions:
    return DataOptions(path=str(path), control_columns=["u"], **keys)


def test_a_file_whose_name_holds_brackets_is_read_as_named_not_as_a_pattern(tmp_path):
    _wide(tmp_path / "rec1.csv", *_sine(301, 0.1), names=("t", "q", "u"))  # what the pattern rec[1].csv matches
    _wide(tmp_path / "rec[1].csv", *_sine(201, 0.1, omega=5.0), names=("t", "q", "u"))
    assert paths_of(tmp_path / "rec[1].csv") == [tmp_path / "rec[1].csv"]
    batch = read_recordings(tmp_path / "rec[1].csv", Recordings(controls=["u"], segment=1.0))
    assert len(batch) == 20 and batch.meta["account"]["pattern"] is False
    assert np.allclose(batch.x[3, :, 0, 0].numpy(), np.sin(5.0 * (3.0 + 0.1 * np.arange(11))), atol=1e-8)
    assert [p.name for p in paths_of(tmp_path / "rec[0-9].csv")] == ["rec1.csv"]  # no such file: a pattern


def test_a_pattern_names_every_file_and_each_one_too_short_to_use(tmp_path, caplog):
    _wide(tmp_path / "a.csv", *_sine(301, 0.1), names=("t", "q", "u"))
    _wide(tmp_path / "b.csv", *_sine(6, 0.1), names=("t", "q", "u"))  # 0.5 s: shorter than a segment
    with caplog.at_level("INFO"):
        splits = load_splits(_opts(tmp_path / "*.csv", segment=1.0), tmp_path, "float64")
    files = splits.train.meta["account"]["files"]
    assert [f["pieces"][0]["segments"] for f in files] == [30, 0]
    said = caplog.text
    assert "pattern " in said and "matched 2 files: a.csv, b.csv" in said
    assert "b.csv: 6 rows, 0–0.5 s; not used: its 6 samples are shorter than one segment (1 s)" in said
    assert "data: train: a.csv 0–22 s; val: a.csv 22–26 s; test: a.csv 26–30 s" in said


def test_a_gap_splits_the_recording_rather_than_being_interpolated(tmp_path, caplog):
    t, q, u = _sine(301, 0.1)
    keep = (t < 9.95) | (t > 12.05)  # 2 s missing after t = 9.9
    _wide(tmp_path / "r.csv", t[keep], q[keep], u[keep], names=("t", "q", "u"))
    for resample in (None, 0.05):
        with caplog.at_level("INFO"):
            data = read_recordings(tmp_path / "r.csv", Recordings(controls=["u"], resample=resample, segment=1.0))
        (gap,) = data.meta["account"]["files"][0]["gaps"]
        assert gap["action"] == "split" and gap["seconds"] == pytest.approx(2.2) and gap["row"] == 100
        starts = [e["t0"] for e in data.meta["segments"]]
        assert starts[:9] == pytest.approx(range(9)) and starts[9] == pytest.approx(12.1)  # none spans the gap
        x = data.x[..., 0, 0].numpy()
        truth = np.sin(2.0 * (np.array(starts)[:, None] + np.asarray(data.t)[None, :]))
        assert np.abs(x - truth).max() < (0.01 if resample else 1e-8)  # the samples of those times, not a filled line
        assert "a gap of 2.2 s (22 steps) before row 101 (t = 9.9 s) splits it" in caplog.text


def test_a_lost_sample_is_filled_only_by_resampling_and_named(tmp_path):
    t, q, u = _sine(101, 0.1)
    keep = np.arange(101) != 50
    _wide(tmp_path / "r.csv", t[keep], q[keep], u[keep], names=("t", "q", "u"))
    filled = read_recordings(tmp_path / "r.csv", Recordings(controls=["u"], segment=1.0, resample=0.1))
    (gap,) = filled.meta["account"]["files"][0]["gaps"]
    assert gap["action"] == "filled" and len(filled) == 10
    assert "filled by data.resample's interpolation" in account_lines(filled.meta["account"])[0]
    split = read_recordings(tmp_path / "r.csv", Recordings(controls=["u"], segment=1.0))  # its own grid: split
    assert split.meta["account"]["files"][0]["gaps"][0]["action"] == "split" and len(split) == 8  # 0–4.9, 5.1–10


def test_unix_epoch_times_lose_no_digit(tmp_path):  # 1.7e9 + 0.05 k failed a step test below float64's resolution
    t, q, u = _sine(401, 0.05)
    _wide(tmp_path / "r.csv", 1.7e9 + t, q, u, names=("t", "q", "u"))
    splits = load_splits(_opts(tmp_path / "r.csv", segment=1.0), tmp_path, "float32")
    assert len(splits.train) == 14 and splits.train.meta["dt"] == pytest.approx(0.05, rel=1e-9)
    assert splits.test.meta["covers"] == "r.csv 17–20 s from its start"
    assert np.allclose(splits.train.x[1, :, 0, 0].numpy(), np.sin(2.0 * (1.0 + 0.05 * np.arange(21))), atol=1e-6)


def test_copies_in_a_pattern_are_refused_naming_both(tmp_path):
    _wide(tmp_path / "a.csv", *_sine(31, 0.1), names=("t", "q", "u"))
    (tmp_path / "b.csv").write_text((tmp_path / "a.csv").read_text().replace(",", ", "))  # same samples, other text
    with pytest.raises(DataError, match=r"b.csv holds the same samples as .*a.csv"):
        read_recordings(tmp_path / "*.csv", Recordings(controls=["u"], segment=1.0))


def test_files_named_txt_or_gzipped_are_recordings_too(tmp_path):
    import gzip

    _wide(tmp_path / "r.txt", *_sine(31, 0.1), names=("t", "q", "u"))
    with gzip.open(tmp_path / "r.csv.gz", "wt") as f:
        f.write((tmp_path / "r.txt").read_text())
    for name in ("r.txt", "r.csv.gz"):
        assert is_recording(tmp_path / name)
        assert len(read_recordings(tmp_path / name, Recordings(controls=["u"], segment=1.0))) == 3


def test_a_specs_inputs_are_read_when_no_control_columns_are_given_and_that_is_said(tmp_path):
    _wide(tmp_path / "r.csv", *_sine(31, 0.1), names=("t", "q", "u"))
    how = Recordings(states=["q", "v"], observed=["q"], rates={"v": "q"}, inputs=["u"], segment=1.0)
    batch = read_recordings(tmp_path / "r.csv", how)
    assert batch.control_names == ["u"] and batch.meta["account"]["inputs_from_spec"]
    assert "inputs ['u'] read from the files' columns of those names" in account_lines(batch.meta["account"])[0]


def test_reading_a_file_too_large_for_memory_is_refused_with_the_advice_that_helps(tmp_path, monkeypatch):
    from mpsim import memory
    from mpsim.errors import ResourceError

    _wide(tmp_path / "r.csv", *_sine(301, 0.1), names=("t", "q", "u"))
    monkeypatch.setattr(memory, "available_bytes", lambda device="cpu": 1000)
    with pytest.raises(ResourceError, match=r"reading r.csv .*split the recording into several files.*data.stride"):
        read_recordings(tmp_path / "r.csv", Recordings(controls=["u"], segment=1.0))
    assert len(read_recordings(tmp_path / "r.csv", Recordings(controls=["u"], segment=1.0, memory_check=False))) == 30


def test_an_input_held_otherwise_than_it_looks_is_warned_about(tmp_path, caplog):
    t = 0.01 * np.arange(400)
    staircase = np.repeat(np.sign(np.sin(np.arange(40))), 10)
    _wide(tmp_path / "stairs.csv", t, np.sin(t), staircase, names=("t", "q", "u"))
    _wide(tmp_path / "smooth.csv", t, np.sin(t), np.sin(20 * t), names=("t", "q", "u"))  # 31 samples a period
    cases = [("stairs.csv", "linear", "is a staircase"), ("smooth.csv", "zoh", "changes smoothly at every sample"),
             ("stairs.csv", "zoh", None), ("smooth.csv", "linear", None)]  # fmt: skip
    for name, hold, said in cases:
        caplog.clear()
        with caplog.at_level("WARNING"):
            read_recordings(tmp_path / name, Recordings(controls=["u"], segment=1.0, input_hold=hold))
        warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
        assert (said is None and not warned) or (len(warned) == 1 and said in warned[0]), (name, hold, warned)
