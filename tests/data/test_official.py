"""A benchmark's own split (`mpsim.data.official`): by file (`data.test_path`) and by row range
(`data.train_range`, `data.val_range`, `data.test_range`), the test records kept whole for free-run evaluation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mpsim.data.pipeline import DataOptions, load_splits
from mpsim.errors import ConfigError, DataError


def _wide(path: Path, n: int, dt: float = 0.02, phase: float = 0.0) -> Path:
    t = dt * np.arange(n)
    rows = "\n".join(f"{a:.6f},{np.sin(3 * a + phase):.9f},{np.cos(a):.9f}" for a in t)
    path.write_text("t,y,u\n" + rows + "\n")
    return path


def test_row_ranges_train_and_test_on_every_file_as_the_benchmark_says(tmp_path):
    for k in (1, 2):
        _wide(tmp_path / f"unif_{k}.csv", 500, phase=k)
    options = DataOptions(
        path=str(tmp_path / "unif_*.csv"),
        control_columns=["u"],
        train_range=[0, 400],
        test_range=[400, 500],
        segment=1.0,
    )
    splits = load_splits(options, tmp_path, "float64")
    assert splits.records is not None and splits.records.x.shape[:2] == (2, 100)  # rows 400–499 of each, whole
    assert [e["length"] for e in splits.records.meta["records"]] == [100, 100]
    assert [e["t0"] for e in splits.records.meta["records"]] == pytest.approx([8.0, 8.0])
    assert np.allclose(splits.records.x[1, :, 0, 0].numpy(), np.sin(3 * (8.0 + 0.02 * np.arange(100)) + 2), atol=1e-8)
    assert len(splits.train) == 14 and len(splits.test) == 2  # 7 one-second segments of rows 0–399 per file
    assert max(e["t0"] for e in splits.train.meta["segments"]) < 7.0  # no training sample from the test rows
    assert splits.val.meta["covers"] == "the training data (no data.val_range)"
    assert splits.test.meta["covers"] == "unif_1.csv rows 400–499 (8–9.98 s), unif_2.csv rows 400–499 (8–9.98 s)"


def test_a_test_file_trains_on_the_others_and_validates_on_their_end(tmp_path):
    _wide(tmp_path / "a.csv", 501)
    _wide(tmp_path / "b.csv", 301, phase=1.0)
    options = DataOptions(
        path=str(tmp_path / "a.csv"), test_path=str(tmp_path / "b.csv"), control_columns=["u"], segment=1.0
    )
    splits = load_splits(options, tmp_path, "float64")
    assert splits.records is not None and splits.records.meta["records"][0]["recording"].endswith("b.csv")
    assert (len(splits.train), len(splits.val), len(splits.test)) == (8, 2, 6)  # a.csv: 10 segments; b.csv: 6
    assert splits.test.meta["covers"] == "b.csv (0–6 s)"


def test_a_range_outside_the_file_or_malformed_is_one_message(tmp_path):
    _wide(tmp_path / "a.csv", 100)
    base = {"path": str(tmp_path / "a.csv"), "control_columns": ["u"]}
    with pytest.raises(DataError, match=r"rows \[50, 200\) asked for, but the recording has 100 rows"):
        load_splits(DataOptions(**base, train_range=[0, 50], test_range=[50, 200]), tmp_path, "float64")
    with pytest.raises(ConfigError, match=r"data.test_range=\[60, 50\]: give the rows \[start, stop\)"):
        load_splits(DataOptions(**base, test_range=[60, 50]), tmp_path, "float64")
    with pytest.raises(ConfigError, match="need a test part"):
        load_splits(DataOptions(**base, train_range=[0, 50]), tmp_path, "float64")


def test_contiguous_splits_keep_their_test_records_whole_too(tmp_path):
    _wide(tmp_path / "a.csv", 501)
    splits = load_splits(
        DataOptions(path=str(tmp_path / "a.csv"), control_columns=["u"], segment=1.0), tmp_path, "float64"
    )
    records = splits.records
    assert records is not None and len(records) == 1  # the test block's segments joined back into one record
    (entry,) = records.meta["records"]
    assert entry["t0"] == pytest.approx(8.0) and entry["length"] == 101
    assert np.allclose(records.x[0, :, 0, 0].numpy(), np.sin(3 * (8.0 + 0.02 * np.arange(101))), atol=1e-8)
