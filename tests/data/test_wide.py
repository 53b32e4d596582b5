"""Wide CSV files as labs write them (`mpsim.data.wide.read_wide_csv`)."""

import numpy as np
import pytest

from mpsim.data.wide import read_wide_csv
from mpsim.errors import DataError


def _file(tmp_path, text, name="rec.csv"):
    path = tmp_path / name
    path.write_bytes(text.encode("utf-8"))
    return path


@pytest.mark.parametrize(
    "text",
    [
        "t,q,u\n0,1,2\n0.5,3,4\n",  # plain
        "t;q;u\n0;1;2\n0.5;3;4\n",  # semicolons
        "t\tq\tu\n0\t1\t2\n0.5\t3\t4\n",  # tabs
        "t   q  u\n 0  1   2\n0.5 3 4\n",  # runs of spaces
        '"t","q","u"\n0,1,2\n0.5,3,4\n',  # quoted header
        "t,q,u,\n0,1,2,\n0.5,3,4,\n",  # a trailing delimiter on every line
        "t,q,u\n0,1,2,\n0.5,3,4,\n",  # ... on the rows only
        " t , q ,u \n0, 1 ,2\n0.5,3 , 4\n",  # spaces around names and values
        "\ufefft,q,u\n0,1,2\n0.5,3,4\n",  # a byte-order mark
        "# rig 3, 2026-01-02\n\nt,q,u\n# restart\n0,1,2\n\n0.5,3,4\n",  # comments and blank lines
        "# t,q,u\n0,1,2\n0.5,3,4\n",  # np.savetxt's header, written as a comment
        "t;q;u\n0;1,0;2\n0,5;3;4,0\n",  # semicolons with decimal commas
        "t,q,u\r\n0,1,2\r\n0.5,3,4\r\n",  # Windows line ends
    ],
)
def test_formats_read_alike(tmp_path, text):
    table = read_wide_csv(_file(tmp_path, text))
    assert table.time_column == "t"
    assert table.t.tolist() == [0.0, 0.5]
    assert table.columns["q"].tolist() == [1.0, 3.0] and table.columns["u"].tolist() == [2.0, 4.0]


def test_named_time_column_and_rows_named_by_line(tmp_path):
    table = read_wide_csv(_file(tmp_path, "# c\ntime,pos\n0,1\n\n1,2\n"), time_column="time")
    assert table.t.tolist() == [0.0, 1.0] and table.row(1) == "row 2 (line 5)"


def test_no_time_column_uses_dt(tmp_path):
    table = read_wide_csv(_file(tmp_path, "q\n1\n2\n3\n"), dt=0.25)
    assert table.t.tolist() == [0.0, 0.25, 0.5] and table.time_column is None and table.dt == 0.25


def test_no_time_column_and_no_dt_names_both_keys(tmp_path):
    with pytest.raises(
        DataError, match=r"no time column 't'.*\['q', 'tt'\].*Did you mean 'tt'.*data.time_column.*data.dt"
    ):
        read_wide_csv(_file(tmp_path, "tt,q\n0,1\n1,2\n"))


def test_an_explicit_time_column_must_exist_even_with_dt(tmp_path):
    with pytest.raises(DataError, match="no time column 'time'"):
        read_wide_csv(_file(tmp_path, "t,q\n0,1\n1,2\n"), time_column="time", dt=0.1)


def test_dt_that_contradicts_the_time_column_is_refused(tmp_path):
    with pytest.raises(DataError, match=r"steps by 0.5 s \(median\) but data.dt=0.1"):
        read_wide_csv(_file(tmp_path, "t,q\n0,1\n0.5,2\n1,3\n"), dt=0.1)


@pytest.mark.parametrize(
    "text, match",
    [
        ("t,q\n0,1\n0.5,2\n0.5,3\n", r"row 3 \(line 4\), time column 't' repeats 0.5 after 0.5.*Sort the rows"),
        ("t,q\n0,1\n0.5,2\n0.2,3\n", r"row 3 \(line 4\), time column 't' goes back to 0.2 after 0.5"),
        ("t,q\n0,1\n,2\n1,3\n", r"row 2 \(line 3\), time column 't' holds nan"),
        ("t,q\n0,1\ninf,2\n", r"row 2 \(line 3\), time column 't' holds inf"),
        ("t,q\n0,1,9\n1,2\n", r"line 2 holds 3 fields separated by ',' but the header line 1 holds 2"),
        ("t,q,q\n0,1,2\n1,2,3\n", r"header names \['q'\] more than once"),
        ("0,1\n1,2\n", r"line 1 holds numbers, not column names"),
        ("\n0.5\n1.5\n", r"line 2 holds numbers, not column names"),
        ("# only a comment\n\n", r"no header and no rows"),
        ("t,q\n", r"a header but no rows"),
        ("t,q\n0,1\n", r"has 1 sample\(s\)"),
    ],
)
def test_bad_files_are_refused_with_file_row_and_fix(tmp_path, text, match):
    path = _file(tmp_path, text)
    with pytest.raises(DataError, match=match) as err:
        read_wide_csv(path)
    assert str(path) in str(err.value)


def test_text_column_is_set_aside_not_refused(tmp_path):
    table = read_wide_csv(_file(tmp_path, "t,q,mode\n0,1,auto\n1,2,manual\n"))
    assert table.columns["q"].tolist() == [1.0, 2.0]
    assert table.unusable["mode"].startswith("row 1 (line 2) holds 'auto', not a number (2 such cells)")


def test_empty_cells_and_inf_are_kept_for_the_mapping_step(tmp_path):
    table = read_wide_csv(_file(tmp_path, "t,q,w\n0,1,\n1,inf,3\n"))
    assert np.isnan(table.columns["w"][0]) and np.isinf(table.columns["q"][1])


def test_not_utf8_and_missing_files_are_refused(tmp_path):
    path = tmp_path / "latin.csv"
    path.write_bytes("t,\xe9\n0,1\n1,2\n".encode("latin-1"))
    with pytest.raises(DataError, match="not UTF-8 text.*Save the file as UTF-8"):
        read_wide_csv(path)
    with pytest.raises(DataError, match="does not exist"):
        read_wide_csv(tmp_path / "nothing.csv")
    with pytest.raises(DataError, match="is a folder"):
        read_wide_csv(tmp_path)


def test_large_file_is_read_exactly(tmp_path):  # its speed is a bench figure, not a timed test
    rows = 131_072
    t = np.arange(rows) / 610.0
    values = np.random.default_rng(0).standard_normal((rows, 3))
    path = tmp_path / "long.csv"
    np.savetxt(path, np.column_stack([t, values]), delimiter=",", header="t,a,b,c", comments="")
    table = read_wide_csv(path)
    assert np.array_equal(table.columns["b"], values[:, 1]) and np.array_equal(table.t, t)
