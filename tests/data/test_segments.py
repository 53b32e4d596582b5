"""Recordings cut into segments and split in time (`mpsim.data.segments`)."""

import pytest
import torch

from mpsim.data.segments import contiguous_split, covers, segment, stack_recordings
from mpsim.data.trajectories import Trajectories
from mpsim.errors import ConfigError, DataError


def _rec(n, dt=0.1, t0=0.0, source="a.csv", controls=True):
    """A recording as `to_recording` makes one: times from its first sample, the file's first time in meta t0."""
    t = dt * torch.arange(n, dtype=torch.float64)
    x = torch.stack([t0 + t, -t0 - t], dim=-1).reshape(1, n, 1, 2)  # states: the file's time and its negative
    u = (10 * (t0 + t)).reshape(1, n, 1, 1) if controls else None
    meta = {
        "source": source,
        "system": source[:-4],
        "state_names": ["q", "v"],
        "control_names": ["u"] if controls else [],
        "dt": dt,
        "t0": [t0],
    }
    return Trajectories(t=t, x=x, edge_index=torch.zeros(2, 0, dtype=torch.long), u=u, meta=meta)


def test_segments_share_end_samples_and_drop_the_tail():
    a, b = _rec(26, t0=5.0, source="a.csv"), _rec(12, source="b.csv")  # 2.5 s and 1.1 s at dt 0.1
    data = segment([a, b], 1.0)  # L = 10: a gives 2 segments (tail 0.5 s dropped), b gives 1
    assert data.x.shape == (3, 11, 1, 2) and data.u.shape == (3, 11, 1, 1)
    assert torch.allclose(data.t, 0.1 * torch.arange(11, dtype=torch.float64))
    assert [(s["recording"], s["index"]) for s in data.meta["segments"]] == [("a.csv", 0), ("a.csv", 1), ("b.csv", 0)]
    assert [s["t0"] for s in data.meta["segments"]] == pytest.approx([5.0, 6.0, 0.0])
    for k, entry in enumerate(data.meta["segments"]):  # absolute time = t0 + t, and the states are those samples
        assert torch.allclose(data.x[k, :, 0, 0], entry["t0"] + data.t) and torch.allclose(
            data.u[k, :, 0, 0], 10 * data.x[k, :, 0, 0]
        )
    assert torch.equal(data.x[0, -1], data.x[1, 0])  # neighbours share their end sample
    assert data.meta["dt"] == pytest.approx(0.1) and data.meta["sources"] == ["a.csv", "b.csv"]
    assert data.meta["source"] == "a.csv, b.csv" and "t0" not in data.meta and data.meta["skipped"] == []


def test_short_recordings_are_skipped_and_named_and_none_left_is_refused():
    data = segment([_rec(26), _rec(5, source="short.csv")], 1.0)
    skipped = [{"recording": "short.csv", "piece": 1, "seconds": pytest.approx(0.4)}]
    assert len(data) == 2 and data.meta["skipped"] == skipped
    assert data.meta["usage"][1] == {"recording": "short.csv", "piece": 1, "segments": 0, "used": 0, "samples": 5}
    assert data.meta["usage"][0] == {"recording": "a.csv", "piece": 1, "segments": 2, "used": 21, "samples": 26}
    with pytest.raises(DataError, match=r"data.segment=3 s is longer than every recording \(the longest lasts 2.5 s\)"):
        segment([_rec(26)], 3.0)
    with pytest.raises(ConfigError, match=r"data.segment=0.01 s is 0.1 steps of 0.1 s.*Use data.segment=0.1\."):
        segment([_rec(26)], 0.01)
    with pytest.raises(DataError, match="longer than every recording"):  # not an OverflowError rounding 1e308/dt
        segment([_rec(26)], 1e308)


def test_a_length_that_rounding_would_change_is_refused_with_the_nearest_two():
    with pytest.raises(
        ConfigError, match=r"0.123 s is 1.23 steps.*differs by 18.7 %.*data.segment=0.1 or data.segment=0.2"
    ):
        segment([_rec(26)], 0.123)
    assert segment([_rec(26)], 1.005).meta["segment"] == pytest.approx(1.0)  # within 1 %: used, and said


def test_recordings_on_different_steps_are_refused_naming_both_files():
    with pytest.raises(DataError, match=r"b.csv is sampled every 0.2 s but a.csv every 0.1 s.*data.resample=<dt>"):
        segment([_rec(30), _rec(30, dt=0.2, source="b.csv")], 1.0)


def test_uneven_grid_and_different_names_are_refused():
    uneven = _rec(30)
    uneven.t = uneven.t + torch.linspace(0, 0.01, 30) ** 2
    with pytest.raises(DataError, match=r"a.csv: the sampling is not uniform.*data.resample"):
        segment([uneven], 1.0)
    with pytest.raises(DataError, match=r"holds states \['q', 'v'\] and inputs \[\]"):
        segment([_rec(30), _rec(30, source="b.csv", controls=False)], 1.0)


def test_whole_recordings_need_equal_lengths():
    data = stack_recordings([_rec(11), _rec(11, t0=3.0, source="b.csv")])
    assert data.x.shape == (2, 11, 1, 2) and float(data.t[0]) == 0.0
    assert [s["t0"] for s in data.meta["segments"]] == [0.0, 3.0]
    with pytest.raises(DataError, match=r"different lengths \{'a.csv': 11, 'b.csv': 12\}.*data.segment=<seconds>"):
        stack_recordings([_rec(11), _rec(12, source="b.csv")])


def test_contiguous_split_keeps_time_order_and_says_what_it_covers():
    data = segment([_rec(71, source="/d/ddp.csv"), _rec(31, source="/d/dircol.csv")], 1.0)  # 7 + 3 segments
    splits = contiguous_split(data, [0.6, 0.2, 0.2])
    assert splits.sizes() == {"train": 6, "val": 2, "test": 2}
    order = [
        (s["recording"], s["t0"]) for part in (splits.train, splits.val, splits.test) for s in part.meta["segments"]
    ]
    assert order == [(s["recording"], s["t0"]) for s in data.meta["segments"]]  # blocks in batch order
    assert splits.train.meta["covers"] == "ddp.csv 0–6 s"
    assert splits.val.meta["covers"] == "ddp.csv 6–7 s, dircol.csv 0–1 s"
    assert splits.test.meta["covers"] == "dircol.csv 1–3 s"
    assert torch.equal(splits.test.x, data.x[8:]) and data.meta.get("covers") is None  # the batch's meta is its own
    only_test = contiguous_split(data, [0, 0, 1], need=("test",))
    assert only_test.sizes() == {"train": 0, "val": 0, "test": 10}
    with pytest.raises(ConfigError, match="gives the val split no segments"):
        contiguous_split(data, [0.5, 0, 0.5])
    with pytest.raises(DataError, match="2 segments cannot be split"):
        contiguous_split(segment([_rec(21)], 1.0), [0.7, 0.15, 0.15])


def test_covers_merges_contiguous_segments_only():
    entries = [{"recording": "a.csv", "t0": t} for t in (0.0, 1.0, 3.0)]
    assert covers(entries, 1.0) == "a.csv 0–2 s, a.csv 3–4 s"
    assert covers([], 1.0) == "nothing"


def test_covers_says_zero_for_a_start_a_hair_off_it():
    # times written to 6 decimals at 8.6 Hz: the fitted uniform grid starts at -1.22e-09 s ("-1.22e-09–325 s")
    assert covers([{"recording": "a.csv", "t0": -1.22e-9}], 5.0) == "a.csv 0–5 s"
