"""Reading a spec file: safe YAML (plain data, no tags that build objects) within `mpsim.safeload`'s bounds.

Imports neither torch nor sympy, so that the command line can refuse a bad spec before a run starts.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

from mpsim.errors import ConfigError
from mpsim.safeload import SPEC_BYTES, BoundedLoader, load_yaml, not_a_regular_file


class _SpecLoader(BoundedLoader):
    """`yaml.SafeLoader` (bounded: `mpsim.safeload`) that also reads `1e-3` and `2E5` as numbers (YAML 1.2 and
    OmegaConf do; PyYAML's YAML 1.1 reads them as text without a dot), so a spec file means what the same keys
    inline in a config mean."""


_SpecLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def load_spec_file(path: str | Path) -> dict[str, Any]:
    """Read a spec from a YAML file (safe loading: plain data only, no tags that build objects), at most
    `SPEC_BYTES` and nested and aliased within the bounds of `mpsim.safeload`.

    Raises:
        ConfigError: the file is missing, not a regular file, unreadable or not a YAML mapping.
        InputLimitError: it is larger, deeper or expands more aliases than mpsim reads.
    """
    path = Path(path)
    why = not_a_regular_file(path)
    if why is not None:
        raise ConfigError(
            f"spec file {path} {why}; give a path to a YAML file (absolute, or relative to the directory you "
            "started mpsim from)."
        )
    fix = "Give a spec of plain states, equations and params (limits: docs/equations.md)"
    try:
        data = load_yaml(path, SPEC_BYTES, f"spec file {path}", fix, loader=_SpecLoader)
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ConfigError(f"cannot read spec file {path}: {first}. Fix the YAML (states, equations, params).") from None
    if not isinstance(data, dict):
        raise ConfigError(
            f"spec file {path} holds a {type(data).__name__}, not a mapping of states, equations, params."
        )
    return data


# ---- the spec ------------------------------------------------------------------------------------------------
