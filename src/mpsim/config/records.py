"""A run's records and names: the overrides it was started with, and the name of its folder."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

from mpsim.errors import DataError
from mpsim.safeload import RECORD_BYTES, load_yaml


def read_overrides_file(run: str | Path) -> list[str] | None:
    """A run's `.hydra/overrides.yaml` (the overrides it was started with) as a list of `key=value` strings, or
    None where the run kept none. A file that is not a YAML list of overrides is a DataError that names it: the
    record is read as data only, and a damaged one is never taken as "no overrides"."""
    path = Path(run) / ".hydra" / "overrides.yaml"
    if not path.exists():
        return None
    fix = "Restore it (a YAML list of key=value overrides, as Hydra wrote it) or move the run away"
    try:  # data only (a python tag is an error, never run), bounded in size, nesting and aliases
        saved = load_yaml(path, RECORD_BYTES, str(path), fix)
    except UnicodeDecodeError as err:
        raise DataError(f"{path} is not valid YAML (not UTF-8 text: {err.reason}). {fix}.") from None
    except OSError as err:
        raise DataError(f"{path} could not be read ({err.strerror or err}). {fix}.") from None
    except yaml.YAMLError as err:
        raise DataError(f"{path} is not valid YAML ({str(err).splitlines()[0]}). {fix}.") from None
    if saved is None:
        return []
    if not isinstance(saved, list) or not all(isinstance(o, str | int | float | bool) for o in saved):
        got = type(saved).__name__ if not isinstance(saved, list) else "a list with nested values"
        raise DataError(f"{path} must be a list of key=value overrides; got {got}. {fix}.")
    return [str(o) for o in saved]


def file_stem(path: str | Path) -> str:
    """A file's name without its suffix, reduced to ``[A-Za-z0-9_.-]`` (a name for runs and systems); may be ""."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", Path(str(path)).stem).strip("._")


def run_name(system_choice: str, data_path: Any = None) -> str:
    """The suffix of a run's directory: the data file's name when the run reads one (`data.path`), else the
    system's (`outputs/train/<date>/<time>_<this>`)."""
    if not data_path:
        return system_choice
    path = Path(str(data_path))
    if any(c in path.name for c in "*?[") and not path.exists():  # a pattern: its fixed part, else its folder's name
        return (
            file_stem(path.name.split("*")[0].split("?")[0].split("[")[0])
            or file_stem(path.parent.name + ".x")
            or "recordings"
        )
    return file_stem(path) or system_choice
