"""The MP-NODE paper's published numbers (`mpsim.report.paper`) come from a data file shipped inside the package."""

import fnmatch
from importlib.resources import files
from pathlib import Path

import tomllib

from mpsim.report.paper import (
    PAPER_TABLE1,
    PAPER_TABLE1_COLUMNS,
    PAPER_TABLE1_RATIOS,
    PAPER_TABLE2,
    SOURCE,
    load_published,
)

PYPROJECT = Path(__file__).resolve().parents[2] / "pyproject.toml"


def test_the_published_numbers_are_the_data_files():
    data = load_published()
    assert PAPER_TABLE2 is not data["table2"] and PAPER_TABLE2 == data["table2"]
    assert PAPER_TABLE2["MP-NODE finetuned"]["Lorenz10 ds=50"] == 632.7
    # an integer stays one, as the paper prints it (a report.csv writes 12800, not 12800.0, where all are integers)
    assert type(PAPER_TABLE2["MP-NODE scratch"]["Gene"]) is int and type(PAPER_TABLE2["L2S"]["Quadrotors"]) is float
    assert PAPER_TABLE1_COLUMNS == ["Validation BA", "Test BA", "Test ER (unseen)", "Test WS (unseen)"]
    assert PAPER_TABLE1 == data["table1"]["rows"] and PAPER_TABLE1["L2S"] == {"Validation BA": "0.0106"}
    # the zero-shot ratios follow from Table 1's means, exactly as 0.0026 / 0.0045 written out
    assert PAPER_TABLE1_RATIOS == {"ER": 0.0026 / 0.0045, "WS": 0.0023 / 0.0045}
    assert list(PAPER_TABLE1_RATIOS) == ["ER", "WS"]


def test_the_package_data_ships_every_published_file():
    published = [p.name for p in files("mpsim.report").joinpath("published").iterdir() if p.name.endswith(".yaml")]
    assert SOURCE == "published/mpnode_paper.yaml" and "mpnode_paper.yaml" in published
    globs = tomllib.loads(PYPROJECT.read_text())["tool"]["setuptools"]["package-data"]["mpsim"]
    for name in published:
        assert any(fnmatch.fnmatch(f"report/published/{name}", g) for g in globs), (name, globs)
