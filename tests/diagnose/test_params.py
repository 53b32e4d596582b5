"""One source for the residual loop's settings and effect kinds: `conf/diagnose.yaml` states exactly the
defaults of `DiagnoseParams`, and an unknown kind is refused."""

import dataclasses
from pathlib import Path

import pytest
import yaml

from mpsim.diagnose.params import DEFAULT_KINDS, KIND_COMPLEXITY, DiagnoseParams
from mpsim.errors import ConfigError

CONF = Path(__file__).resolve().parents[2] / "src" / "mpsim" / "conf" / "diagnose.yaml"


def test_diagnose_yaml_states_the_schema_defaults():
    stated = yaml.safe_load(CONF.read_text())["diagnose"]
    defaults = dataclasses.asdict(DiagnoseParams())
    assert stated == defaults


def test_effect_kinds_are_one_list():
    assert DEFAULT_KINDS == list(KIND_COMPLEXITY)
    import mpsim.effects as fx

    assert all(isinstance(getattr(fx, k, None), type) for k in DEFAULT_KINDS)  # each is an effect class


def test_an_unknown_kind_is_refused_with_a_suggestion():
    with pytest.raises(ConfigError, match="'LinearDamping'"):
        DiagnoseParams(kinds=["LinearDampin"])
