"""One source per default and per list: a config schema that mirrors a constructor states exactly its defaults,
and every list of effect kinds is read from `mpsim.diagnose.params.KIND_COMPLEXITY`."""

from __future__ import annotations

import dataclasses
import importlib
import inspect

import pytest

import mpsim.config as config
import mpsim.effects as fx
from mpsim.data.dataset import DatasetSpec
from mpsim.diagnose.library import DEFAULT_KINDS as LIBRARY_KINDS
from mpsim.diagnose.params import DEFAULT_KINDS, KIND_COMPLEXITY, DiagnoseParams
from mpsim.models.mpnode import MPNODE
from mpsim.models.smnn_discovery import SMNNDiscovery


def _targeted_schemas() -> list[type]:
    """The schema dataclasses of `mpsim.config` that name the class they configure (`_target_`)."""
    found = []
    for obj in vars(config).values():
        if inspect.isclass(obj) and dataclasses.is_dataclass(obj):
            if any(f.name == "_target_" for f in dataclasses.fields(obj)):
                found.append(obj)
    return found


def _default(f: dataclasses.Field) -> object:
    return f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default


def test_there_is_a_targeted_schema():
    assert config.TrainerConf in _targeted_schemas()


@pytest.mark.parametrize("schema", _targeted_schemas(), ids=lambda s: s.__name__)
def test_a_targeted_schema_states_its_constructors_defaults(schema):
    fields = {f.name: _default(f) for f in dataclasses.fields(schema)}
    module, _, name = fields.pop("_target_").rpartition(".")
    target = getattr(importlib.import_module(module), name)
    params = inspect.signature(target).parameters
    assert fields == {k: p.default for k, p in params.items()}


def test_the_data_schema_states_the_dataset_defaults():
    data = {f.name: _default(f) for f in dataclasses.fields(config.DataConf)}
    spec = {f.name: f.default for f in dataclasses.fields(DatasetSpec) if f.default is not dataclasses.MISSING}
    renamed = {"rtol": "gt_rtol", "atol": "gt_atol"}  # the ground-truth tolerances
    assert {k: data[renamed.get(k, k)] for k in spec} == spec


def test_the_diagnose_schema_is_the_library_argument():
    assert config.DiagnoseConf.__dataclass_fields__["diagnose"].default_factory is DiagnoseParams


def test_every_effect_class_is_a_library_kind_and_every_list_reads_the_one_list():
    classes = {
        name
        for name, obj in vars(fx).items()
        if inspect.isclass(obj)
        and issubclass(obj, fx.Effect)
        and obj is not fx.Effect
        and obj.__module__ == fx.__name__
    }
    assert classes == set(KIND_COMPLEXITY)
    assert list(LIBRARY_KINDS) == DEFAULT_KINDS == list(KIND_COMPLEXITY)
    assert DiagnoseParams().kinds == DEFAULT_KINDS
    declared = {*MPNODE.represents, *MPNODE.indistinguishable, *SMNNDiscovery(3, degree=3).represents}
    assert declared <= set(KIND_COMPLEXITY)
