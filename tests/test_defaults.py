"""One source per default and per list: a config schema that mirrors a constructor states exactly its defaults,
every `_target_` node of the shipped YAML configs states its constructor's defaults (or is allow-listed below as
a deliberate difference), and every list of effect kinds is read from `mpsim.diagnose.params.KIND_COMPLEXITY`."""

from __future__ import annotations

import dataclasses
import importlib
import inspect
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from omegaconf import DictConfig, ListConfig, OmegaConf

import mpsim
import mpsim.config as config
import mpsim.effects as fx
from mpsim.data.dataset import DatasetSpec
from mpsim.diagnose.library import DEFAULT_KINDS as LIBRARY_KINDS
from mpsim.diagnose.params import DEFAULT_KINDS, KIND_COMPLEXITY, DiagnoseParams
from mpsim.models.mpnode import MPNODE
from mpsim.models.smnn_discovery import SMNNDiscovery
from mpsim.systems.gene import default_gene_graph_params
from mpsim.systems.kuramoto import default_kuramoto_graph_params

CONF = Path(mpsim.__file__).parent / "conf"

# Deliberate differences between a YAML `_target_` node and its constructor's defaults: (file under conf/, dotted
# path of the node in the file, "" for the top) -> the keys that may differ. Every listed key must still differ
# (`test_the_allow_list_is_not_stale`), so an entry goes when the difference does.
DELIBERATE: dict[tuple[str, str], set[str]] = {
    # Named instances of a class whose constructor defaults are another named instance (quad3, nbody100,
    # gene_ba_small, kuramoto10_ba, dopri5): these keys are what makes the instance.
    ("system/quad6.yaml", ""): {"name", "n_quads"},
    ("system/nbody.yaml", "system"): {"name"},
    ("system/nbody20.yaml", "system"): {"name", "n_particles"},
    ("system/nbody1000.yaml", "system"): {"name", "n_particles"},
    ("system/nbody100_coulomb.yaml", "system"): {"name", "force"},
    ("system/nbody1000_coulomb.yaml", "system"): {"name", "n_particles", "force"},
    ("system/gene_ba_large.yaml", ""): {"name", "n_nodes"},
    ("system/gene_er_small.yaml", ""): {"name", "graph"},
    ("system/gene_er_large.yaml", ""): {"name", "n_nodes", "graph"},
    ("system/gene_ws_small.yaml", ""): {"name", "graph"},
    ("system/gene_ws_large.yaml", ""): {"name", "n_nodes", "graph"},
    ("system/kuramoto10_er.yaml", ""): {"name", "graph"},
    ("system/kuramoto10_ws.yaml", ""): {"name", "graph"},
    ("solver/rk4.yaml", ""): {"method"},
    # An experiment's effect is the experiment: an effect's constructor defaults are the zero effect on state 0.
    ("experiment/lorenz3_forced.yaml", "system.effects.0"): {"amplitude", "omega", "target"},
    ("experiment/lorenz_cubic_discovery.yaml", "system.effects.0"): {"coef", "target"},
    ("experiment/pendulum_damped.yaml", "system.effects.0"): {"coef", "target"},
}

# Constructor defaults of None that stand for a value computed from the other arguments: the YAML states that
# value, so it is compared with the computation (on the node's arguments over the constructor's defaults).
COMPUTED: dict[tuple[str, str], Callable[[dict[str, Any]], Any]] = {
    ("mpsim.systems.gene.GeneRegulation", "graph_params"): lambda a: default_gene_graph_params(
        a["graph"], a["n_nodes"]
    ),
    ("mpsim.systems.kuramoto.Kuramoto", "graph_params"): lambda a: default_kuramoto_graph_params(a["graph"]),
}


def _target_nodes(node: Any, path: tuple[str, ...] = ()) -> Iterator[tuple[str, DictConfig]]:
    """(dotted path, node) of every mapping with a `_target_` in a loaded YAML file, nested ones included."""
    if isinstance(node, DictConfig) and "_target_" in node:
        yield ".".join(path), node
    if isinstance(node, (DictConfig, ListConfig)):
        keys = node.keys() if isinstance(node, DictConfig) else range(len(node))
        for key in keys:
            yield from _target_nodes(node._get_node(key), (*path, str(key)))


def _yaml_target_nodes() -> list[tuple[str, str, DictConfig]]:
    return [
        (str(f.relative_to(CONF)), path, node)
        for f in sorted(CONF.rglob("*.yaml"))
        for path, node in _target_nodes(OmegaConf.load(f))
    ]


def _plain(value: Any) -> Any:
    """Lists for tuples, recursively, so that YAML lists compare with tuple defaults."""
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


def _differences(node: DictConfig) -> dict[str, str]:
    """key -> why, for each key of a `_target_` node that is not its constructor's parameter or default."""
    target_name = str(node._target_)
    module, _, name = target_name.rpartition(".")
    params = inspect.signature(getattr(importlib.import_module(module), name)).parameters
    takes_any = any(p.kind == p.VAR_KEYWORD for p in params.values())
    defaults = {k: p.default for k, p in params.items() if p.default is not inspect.Parameter.empty}
    args = {**defaults, **OmegaConf.to_container(node, resolve=False)}  # type: ignore[dict-item]
    out = {}
    for key in (str(k) for k in node.keys() if not str(k).startswith("_")):
        if key not in params:
            if not takes_any:
                out[key] = f"not a parameter of {target_name}"
            continue
        if key not in defaults:  # required: the YAML is the only source
            continue
        if OmegaConf.is_interpolation(node, key):
            out[key] = f"{node._get_node(key)._value()} (an interpolation) vs the default {defaults[key]!r}"
            continue
        default = defaults[key]
        if (target_name, key) in COMPUTED and default is None:
            default = COMPUTED[target_name, key](args)
        if _plain(args[key]) != _plain(default):
            out[key] = f"{args[key]!r} vs the default {default!r}"
    return out


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
        and obj.__module__.startswith(fx.__name__ + ".")
        and not name.startswith("_")  # a private base (the phase couplings' `_PhaseCoupling`) is no kind
    }
    assert classes == set(KIND_COMPLEXITY)
    assert list(LIBRARY_KINDS) == DEFAULT_KINDS == list(KIND_COMPLEXITY)
    assert DiagnoseParams().kinds == DEFAULT_KINDS
    declared = {*MPNODE.represents, *MPNODE.indistinguishable, *SMNNDiscovery(3, degree=3).represents}
    assert declared <= set(KIND_COMPLEXITY)


@pytest.mark.parametrize(
    ("file", "path", "node"), [pytest.param(*n, id=f"{n[0]}:{n[1]}" if n[1] else n[0]) for n in _yaml_target_nodes()]
)
def test_a_yaml_target_node_states_its_constructors_defaults(file, path, node):
    """Every `_target_` node of conf/**.yaml: each key is a parameter of the target, and its value is the
    constructor's default unless DELIBERATE lists it (one source for each default)."""
    allowed = DELIBERATE.get((file, path), set())
    assert {k: why for k, why in _differences(node).items() if k not in allowed} == {}


def test_the_allow_list_is_not_stale():
    nodes = {(file, path): node for file, path, node in _yaml_target_nodes()}
    assert set(DELIBERATE) <= set(nodes)
    assert all(keys <= set(_differences(nodes[where])) for where, keys in DELIBERATE.items())
