"""Mapping a file's columns to a model's states and inputs (`mpsim.data.recording.to_recording`)."""

import numpy as np
import pytest
import torch

from mpsim.data.recording import to_recording
from mpsim.data.wide import read_wide_csv
from mpsim.errors import DataError


@pytest.fixture
def table(tmp_path):
    path = tmp_path / "axis_run.csv"
    path.write_text("time,qm,speed,vir,mode\n0.0,1,10,0.5,a\n0.1,2,20,0.6,b\n0.21,3,30,0.7,c\n")
    return read_wide_csv(path, time_column="time")


def test_columns_are_picked_renamed_and_ordered(table):
    rec = to_recording(table, {"q": "qm", "u": "vir", "v": "speed"}, ["v", "q"], ["u"])
    assert rec.x.shape == (1, 3, 1, 2) and rec.u.shape == (1, 3, 1, 1) and rec.n_nodes == 1
    assert rec.x[0, :, 0, 0].tolist() == [10.0, 20.0, 30.0] and rec.x[0, :, 0, 1].tolist() == [1.0, 2.0, 3.0]
    assert rec.t.dtype == torch.float64 and rec.t.tolist() == [0.0, 0.1, 0.21]  # the file's own (jittery) times
    assert rec.meta["system"] == "axis_run" and rec.meta["source"] == table.source
    assert rec.meta["state_names"] == ["v", "q"] and rec.meta["control_names"] == ["u"]
    assert rec.meta["columns"] == {"v": "speed", "q": "qm", "u": "vir"}
    assert rec.meta["t0"] == [0.0] and rec.meta["dt"] == pytest.approx(0.105)


def test_names_not_in_the_mapping_are_looked_up_as_themselves(table):
    rec = to_recording(table, None, ["qm"])
    assert rec.u is None and rec.state_names == ["qm"]


def test_unknown_column_lists_the_files_columns_with_a_did_you_mean(table):
    with pytest.raises(
        DataError,
        match=r"no column for 'v' \(mapped to column 'sped' by data.columns\); the file's "
        r"columns are \['mode', 'qm', 'speed', 'time', 'vir'\]\. Did you mean 'speed'\?.*data.observed",
    ):
        to_recording(table, {"v": "sped"}, ["v"])
    with pytest.raises(DataError, match=r"no column for 'q'; the file's columns"):
        to_recording(table, None, ["q"])


def test_text_column_is_refused_with_its_first_cell(table):
    with pytest.raises(DataError, match=r"'mode'.*cannot be used: it is row 1 \(line 2\) holds 'a'"):
        to_recording(table, None, ["mode"])


def test_non_finite_values_are_refused_with_row_line_and_column(tmp_path):
    path = tmp_path / "gap.csv"
    path.write_text("t,q,u\n0,1,0\n1,,0\n2,3,inf\n")
    table = read_wide_csv(path)
    with pytest.raises(DataError, match=r"row 2 \(line 3\), column 'q' \(for 'q'\) is empty or NaN .*Remove or interp"):
        to_recording(table, None, ["q"])
    with pytest.raises(DataError, match=r"row 3 \(line 4\), column 'u' \(for 'u'\) holds inf"):
        to_recording(table, {"q": "t"}, ["q"], ["u"])
    assert np.isnan(table.columns["q"][1])  # the table is unchanged


def test_no_state_is_refused(table):
    with pytest.raises(DataError, match="no state to read"):
        to_recording(table, None, [])
