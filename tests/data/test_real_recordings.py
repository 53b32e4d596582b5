"""The data steps on seven real recordings: a torque-driven pendulum from the DFKI lab (issue 60, case a).

The files live in ``shared/data/real/dfki_simple_pendulum/`` beside the repository (or beside a folder above it);
the tests skip where it is absent. Columns ``time, position, velocity, torque``; the time grids jitter by up to
1.5 % of a step, ``sac_200Hz.csv`` has a 22 ms first step, ``sysid_pd_300Hz.csv`` jitters by 7 %.
"""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from mpsim.data.grid import resample, stride, uniform_or_refuse
from mpsim.data.latent import estimate_latent
from mpsim.data.noise import noise_summary
from mpsim.data.recording import to_recording
from mpsim.data.segments import contiguous_split, segment
from mpsim.data.wide import read_wide_csv
from mpsim.errors import DataError

COLUMNS = {"q": "position", "v": "velocity", "tau": "torque"}
DT, SECONDS = 0.01, 1.0


def _folder() -> Path | None:
    for parent in Path(__file__).resolve().parents:
        folder = parent / "shared" / "data" / "real" / "dfki_simple_pendulum"
        if folder.is_dir():
            return folder
    return None


FOLDER = _folder()
pytestmark = pytest.mark.skipif(
    FOLDER is None, reason="shared/data/real/dfki_simple_pendulum is not beside the repository"
)


@pytest.fixture(scope="module")
def files():
    paths = sorted(FOLDER.glob("*.csv"))
    assert len(paths) == 7
    return paths


@pytest.fixture(scope="module")
def recordings(files):
    return [to_recording(read_wide_csv(p, time_column="time"), COLUMNS, ["q", "v"], ["tau"]) for p in files]


def test_reading_keeps_every_sample_of_the_file(files, recordings):
    for path, rec in zip(files, recordings, strict=True):
        raw = pd.read_csv(path)
        assert rec.x.shape == (1, len(raw), 1, 2) and rec.u.shape == (1, len(raw), 1, 1)
        assert np.array_equal(rec.t.numpy(), raw["time"].to_numpy())
        assert np.array_equal(rec.x[0, :, 0, 0].numpy(), raw["position"].to_numpy())
        assert np.array_equal(rec.u[0, :, 0, 0].numpy(), raw["torque"].to_numpy())
        assert rec.meta["system"] == path.stem and rec.meta["t0"] == [0.0]


def test_jitter_check_accepts_five_files_and_refuses_the_damaged_two(recordings):
    refused = []
    for rec in recordings:
        try:
            uniform_or_refuse(rec)
        except DataError as err:
            assert "data.resample=" in str(err)
            refused.append(Path(rec.meta["source"]).name)
    assert refused == ["sac_200Hz.csv", "sysid_pd_300Hz.csv"]


def test_stride_keeps_the_files_rows(files, recordings):
    rec = stride(recordings[0], 5)  # ddp at 500 Hz -> 100 Hz
    raw = pd.read_csv(files[0]).iloc[::5]
    assert np.array_equal(rec.x[0, :, 0, 1].numpy(), raw["velocity"].to_numpy())


def test_resample_and_segment_all_seven(files, recordings):
    resampled = [resample(rec, DT) for rec in recordings]
    data = segment(resampled, SECONDS)
    length = round(SECONDS / DT)
    expected = [(r.n_times - 1) // length for r in resampled]
    assert expected == [5, 3, 19, 19, 19, 40, 3]  # ddp 6 s, dircol 3.5 s, es 20 s, es_1kg, ilqr, sac 40 s, sysid 3.9 s
    assert data.x.shape == (sum(expected), length + 1, 1, 2) and data.u.shape[0] == sum(expected)
    raw = {str(p): pd.read_csv(p) for p in files}
    for k in (0, 7, 50, len(data) - 1):  # values are the file's, interpolated at t0 + t
        entry = data.meta["segments"][k]
        frame = raw[entry["recording"]]
        times = entry["t0"] + data.t.numpy()
        for name, column in (("q", "position"), ("v", "velocity")):
            want = np.interp(times, frame["time"], frame[column])
            assert np.allclose(data.x[k, :, 0, ["q", "v"].index(name)].numpy(), want, rtol=0, atol=1e-9)
        assert np.allclose(
            data.u[k, :, 0, 0].numpy(), np.interp(times, frame["time"], frame["torque"]), rtol=0, atol=1e-9
        )
    splits = contiguous_split(data, [0.7, 0.15, 0.15])
    assert splits.sizes() == {"train": 76, "val": 16, "test": 16}
    assert splits.val.meta["covers"] == "sac_200Hz.csv 11–27 s"


def test_velocity_estimated_from_position_matches_the_measured_one(recordings):
    measured = resample(recordings[0], DT)  # ddp: smooth torque, velocity noise about 0.15 rad/s
    positions = measured.subset([0])
    positions = type(positions)(
        t=positions.t,
        x=positions.x[..., :1],
        edge_index=positions.edge_index,
        meta={**positions.meta, "state_names": ["q"]},
    )
    estimated = estimate_latent(positions, {"v": "q"}, states=["q", "v"])
    v_measured, v_estimated = measured.x[0, :, 0, 1], estimated.x[0, :, 0, 1]
    assert float(torch.corrcoef(torch.stack([v_measured, v_estimated]))[0, 1]) > 0.995
    assert float((v_measured - v_estimated).pow(2).mean().sqrt()) < 0.15  # below the measured velocity's own noise


def test_quantisation_steps_are_the_encoders(recordings):
    for rec in recordings:  # the same converters in every file
        summary = noise_summary(rec)
        assert summary["q"]["quantum"] == pytest.approx(0.002914, rel=1e-3)
        assert summary["v"]["quantum"] == pytest.approx(0.02198, rel=1e-3)
        assert summary["tau"]["quantum"] == pytest.approx(0.008791, rel=1e-3)
        assert summary["q"]["std"] < 0.002  # at the encoder's rounding floor, step/√12 = 0.00084, or near it
