"""The MP-NODE paper's published numbers, which the layouts print beside the runs' own: read from the data file
`published/mpnode_paper.yaml` inside this package (shipped as package data), never written in code."""

from __future__ import annotations

from importlib.resources import files
from typing import Any

import yaml

#: the data file, relative to the `mpsim.report` package
SOURCE = "published/mpnode_paper.yaml"


def load_published(name: str = SOURCE) -> dict[str, Any]:
    """A published-numbers file of this package as a mapping (YAML read as data only)."""
    return yaml.safe_load(files("mpsim.report").joinpath(name).read_text(encoding="utf-8"))


def _mean(cell: str) -> float:
    """The mean of a published "mean ± std" cell ("0.0026 ± 0.0008" → 0.0026)."""
    return float(cell.split("±")[0])


_PAPER = load_published()

#: the paper's Table 2 (epochs to the minimum test error × that error), row → column → value
PAPER_TABLE2: dict[str, dict[str, float]] = _PAPER["table2"]
#: the paper's Table 1 (gene 4×4, trained on BA with 5 adjacency matrices), row → column → "mean ± std" as printed
PAPER_TABLE1: dict[str, dict[str, str]] = _PAPER["table1"]["rows"]
PAPER_TABLE1_COLUMNS: list[str] = _PAPER["table1"]["columns"]
#: the paper's Table 1 ratios of each unseen graph's test error to the training graph's (MP-NODE), e.g. ER:
#: 0.0026 / 0.0045
PAPER_TABLE1_RATIOS: dict[str, float] = {
    column.split()[1]: _mean(PAPER_TABLE1["MP-NODE"][column])
    / _mean(PAPER_TABLE1["MP-NODE"][f"Test {_PAPER['table1']['trained_on']}"])
    for column in PAPER_TABLE1_COLUMNS
    if column.endswith("(unseen)")
}
