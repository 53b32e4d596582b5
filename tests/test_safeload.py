"""Bounded reading of YAML and JSON (`mpsim.safeload`): alias bombs, deep nesting, oversized files and named pipes
are refused before they can hang mpsim; ordinary files read as before."""

from __future__ import annotations

import json
import os
import time
import tracemalloc
from pathlib import Path

import pytest
import yaml

from mpsim import safeload
from mpsim.errors import DataError
from mpsim.safeload import (
    ALIAS_NODES,
    MAX_DEPTH,
    MIB,
    InputLimitError,
    json_depth,
    load_json,
    load_yaml,
    not_a_regular_file,
    parse_json,
    parse_yaml,
    read_text,
)


def billion_laughs(levels: int = 9, width: int = 9) -> str:
    """The classic alias bomb: each level a list of `width` aliases of the level below (width**levels values)."""
    lines = [f"a0: &a0 [{', '.join(['lol'] * width)}]"]
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * width)}]" for i in range(1, levels + 1)]
    return "\n".join(lines) + f"\nlaughs: *a{levels}\n"


def test_a_billion_laughs_is_refused_while_composing_in_well_under_a_second():
    text = billion_laughs()
    assert len(text) < 1500  # 1.3 KB that would expand to 9**10 (3.5 billion) values
    tracemalloc.start()
    start = time.perf_counter()
    try:
        with pytest.raises(InputLimitError, match=f"repeat more than {ALIAS_NODES:,} values by line") as err:
            parse_yaml(text, "spec file bomb.yaml", "Fix it")
        elapsed = time.perf_counter() - start
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert str(err.value).startswith("spec file bomb.yaml: its anchors and aliases")
    assert str(err.value).endswith("write the values out instead. Fix it.")
    assert elapsed < 5  # milliseconds in practice; generous for a loaded machine
    assert peak < 20 * MIB  # refused while composing, before anything is expanded


def test_aliases_within_the_bound_still_load():
    text = "base: &b {x: 1, y: [1, 2]}\nc:\n  <<: *b\n  z: 3\nd: *b\n"
    assert parse_yaml(text, "f", "fix") == {
        "base": {"x": 1, "y": [1, 2]},
        "c": {"x": 1, "y": [1, 2], "z": 3},
        "d": {"x": 1, "y": [1, 2]},
    }
    # an alias counts every value it repeats, lists included: 2 levels of 9 repeat 1 729 values, 3 levels 15 670
    assert len(parse_yaml(billion_laughs(levels=2), "f", "fix")["laughs"]) == 9
    with pytest.raises(InputLimitError, match="repeat more than 10,000 values by line 5"):
        parse_yaml(billion_laughs(levels=3), "f", "fix")


def test_an_alias_inside_the_node_it_names_is_refused():
    with pytest.raises(InputLimitError, match="the alias at line 1 names a node that contains it"):
        parse_yaml("a: &a [1, *a]\n", "f", "fix")


@pytest.mark.parametrize("depth", [MAX_DEPTH, MAX_DEPTH + 1, 100_000])
def test_nesting_is_bounded_in_yaml_and_json_alike(depth):
    text = "[" * depth + "1" + "]" * depth
    if depth <= MAX_DEPTH:
        assert json_depth(text) == depth
        assert parse_json(text, "f", "fix", MIB) == parse_yaml(text, "f", "fix")
        return
    start = time.perf_counter()
    with pytest.raises(InputLimitError, match=f"over mpsim's limit of {MAX_DEPTH}; flatten it. fix."):
        parse_json(text, "f", "fix", MIB)
    with pytest.raises(InputLimitError, match=f"more than {MAX_DEPTH} levels deep by line 1"):
        parse_yaml(text, "f", "fix")
    assert time.perf_counter() - start < 5  # no recursion into 100 000 levels


def test_json_depth_ignores_brackets_inside_strings():
    text = json.dumps({"a": "[[[[{{{{" * 50, "b": ['"]]]', [[1]]], "c": '\\"[[['})
    assert json_depth(text) == 4  # {, the list, and [[1]] in it
    assert parse_json(text, "f", "fix", MIB)["a"].startswith("[[[[")


def test_size_is_checked_before_reading(tmp_path):
    path = tmp_path / "big.json"
    path.write_text('{"pad": "' + "x" * (2 * MIB) + '"}')
    with pytest.raises(
        InputLimitError, match=r"big.json is 2 MB, over mpsim's limit of 1 MB for this file. Shrink it."
    ):
        load_json(path, MIB, str(path), "Shrink it")
    assert load_json(path, 4 * MIB, str(path), "Shrink it")["pad"] == "x" * (2 * MIB)
    with pytest.raises(InputLimitError, match="over mpsim's limit of 0.5 MB"):
        parse_json(path.read_text(), "text", "Shrink it", MIB // 2)


def test_a_named_pipe_is_refused_without_being_opened(tmp_path):
    pipe = tmp_path / "pipe.yaml"
    os.mkfifo(pipe)  # opening it for reading would block until a writer came
    assert not_a_regular_file(pipe) == "is a named pipe (FIFO), not a regular file"
    with pytest.raises(DataError, match="spec file .*pipe.yaml is a named pipe"):
        load_yaml(pipe, MIB, f"spec file {pipe}", "fix")
    assert not_a_regular_file(tmp_path) == "is a folder, not a file"
    assert not_a_regular_file(tmp_path / "none") == "does not exist"
    with pytest.raises(FileNotFoundError):
        read_text(tmp_path / "none", MIB, "f", "fix")


def test_plain_files_load_as_yaml_safe_load_and_json_load_read_them(tmp_path):
    record = "- system=lorenz3\n- trainer.lr=0.001\n- 'data.split=[0.8, 0.1, 0.1]'\n"
    (tmp_path / "o.yaml").write_text(record)
    assert load_yaml(tmp_path / "o.yaml", MIB, "o", "fix") == yaml.safe_load(record)
    summary = {"task": "train", "test": {"rmse": 0.1, "horizons": {"1": [0.1, 0.2]}}, "x": [None, True, "é"]}
    (tmp_path / "s.json").write_text(json.dumps(summary))
    assert load_json(tmp_path / "s.json", MIB, "s", "fix") == summary


def test_yaml_stays_plain_data():
    with pytest.raises(yaml.YAMLError):
        parse_yaml("!!python/object/apply:os.system ['true']\n", "f", "fix")


def test_the_limits_are_the_documented_ones():
    docs = (Path(__file__).parents[1] / "docs" / "guarantees.md").read_text()
    for name in ("SPEC_BYTES", "RECORD_BYTES", "META_BYTES", "SUMMARY_BYTES"):
        assert f"{safeload.size_text(getattr(safeload, name))}" in docs, name
    assert f"{MAX_DEPTH} levels" in docs and f"{ALIAS_NODES:,} values" in docs
