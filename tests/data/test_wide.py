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


def test_a_hash_inside_a_text_cell_stays_in_the_cell(tmp_path):  # pandas' comment='#' cut the row there
    table = read_wide_csv(_file(tmp_path, "# rig 3\nt,note,q\n0,take #3,1\n# pause\n1,ok,2\n"))
    assert table.columns["q"].tolist() == [1.0, 2.0] and "take #3" in table.unusable["note"]
    assert table.row(1) == "row 2 (line 5)"  # comment lines are not rows; lines are counted when named


def test_decimal_commas_after_the_first_rows_are_found(tmp_path):  # the first 50 rows were all whole numbers
    rows = [f"{k};{k};1" for k in range(60)] + ["60;60,5;1,25"]
    table = read_wide_csv(_file(tmp_path, "t;q;u\n" + "\n".join(rows) + "\n"))
    assert table.columns["q"][-1] == 60.5 and table.columns["u"][-1] == 1.25


def test_iso_dates_in_the_time_column_are_seconds_since_the_first(tmp_path):
    text = "time,q\n2026-01-02 10:00:00.00,1\n2026-01-02 10:00:00.05,2\n2026-01-02T10:00:00.10,3\n"
    table = read_wide_csv(_file(tmp_path, text), time_column="time")
    assert np.allclose(table.t, [0.0, 0.05, 0.1]) and table.time_origin == "2026-01-02 10:00:00"


@pytest.mark.parametrize(
    "text, match",
    [
        ("t,q\n0,1\n0.5s,2\n1,3\n", r"row 2 \(line 3\), time column 't' holds '0.5s'.*a number with a unit"),
        ("t,q\n0,1\n0.5,2\ntotal,3 rows\n", r"row 3 \(line 4\) holds text in every column.*a footer"),
        ("t,q\n0,1\nt,q\n1,2\n", r"row 2 \(line 3\) repeats the header.*several recordings joined"),
        ("t,q\n0,1\nsee note,n/a\n1,2\n", r"row 2 \(line 3\) holds text in every column.*between rows of numbers"),
    ],
)
def test_text_where_numbers_belong_is_named_by_row_with_its_fix(tmp_path, text, match):
    with pytest.raises(DataError, match=match):
        read_wide_csv(_file(tmp_path, text))


def test_a_time_column_not_named_t_is_not_ignored_for_data_dt(tmp_path):
    path = _file(tmp_path, "time,q\n0,1\n0.1,2\n2.2,3\n")  # a 2 s gap that t = k·dt would stitch across
    with pytest.raises(DataError, match=r"column 'time' looks like the file's times.*data.time_column=time"):
        read_wide_csv(path, dt=0.1)
    with pytest.raises(DataError, match=r"no time column 't'.*Column 'time' looks like the times"):
        read_wide_csv(path)
    assert read_wide_csv(path, time_column=None, dt=0.1).t.tolist() == pytest.approx([0.0, 0.1, 0.2])  # said so


def test_a_gzipped_csv_is_read_as_its_text(tmp_path):
    import gzip

    path = tmp_path / "rec.csv.gz"
    with gzip.open(path, "wt") as f:
        f.write("t,q\n0,1\n0.5,3\n")
    assert read_wide_csv(path).columns["q"].tolist() == [1.0, 3.0]
