"""Every config option composes and instantiates; typos and wrong types fail at start with a clear message."""

from pathlib import Path

import pytest
from hydra.errors import ConfigCompositionException
from hydra.utils import instantiate

import mpsim
from mpsim.config import check_targets
from mpsim.errors import ConfigError
from mpsim.models.base import Model
from mpsim.systems.base import System

CONF = Path(mpsim.__file__).parent / "conf"


def _options(group):
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


@pytest.mark.parametrize("name", _options("system"))
def test_every_system_builds(cfg_factory, name):
    cfg = cfg_factory("train", f"system={name}")
    check_targets(cfg)
    system = instantiate(cfg.system)
    assert isinstance(system, System) and system.name == name
    assert system.rhs is not None and system.n_nodes >= 1


@pytest.mark.parametrize("name", _options("model"))
def test_every_model_builds(cfg_factory, name):
    cfg = cfg_factory("train", f"model={name}")
    solver = instantiate(cfg.solver)
    assert isinstance(instantiate(cfg.model, state_dim=2, control_dim=0, solver=solver), Model)


@pytest.mark.parametrize("group", ["solver", "trainer", "mode", "experiment"])
def test_every_option_of_the_other_groups_composes(cfg_factory, group):
    for name in _options(group):
        cfg = cfg_factory("train", f"{group}={name}")
        if group in cfg and "_target_" in cfg[group]:
            instantiate(cfg[group])


@pytest.mark.parametrize("command", ["train", "eval", "simulate", "report"])
def test_primary_configs_compose(cfg_factory, command):
    extra = ["init=x.ckpt"] if command == "eval" else []
    assert cfg_factory(command, *extra).task == command


def test_typo_in_a_target_node_suggests_the_right_key(cfg_factory):
    with pytest.raises((ConfigError, ConfigCompositionException), match="n_nodes"):
        cfg = cfg_factory("train", "system=lorenz3", "+system.n_node=4")
        check_targets(cfg)


def test_wrong_type_in_a_target_node(cfg_factory):
    cfg = cfg_factory("train", "system=lorenz3", "system.coupling=strong")
    with pytest.raises(ConfigError, match=r"system.coupling='strong' has the wrong type: .* expects float"):
        check_targets(cfg)


def test_typed_schema_rejects_typos_and_wrong_types(cfg_factory):
    with pytest.raises(ConfigCompositionException, match="trainer.lrr"):
        cfg_factory("train", "trainer.lrr=0.1")
    with pytest.raises(ConfigCompositionException, match="max_epochs"):
        cfg_factory("train", "trainer.max_epochs=many")
    with pytest.raises(ConfigCompositionException, match="n_train"):
        cfg_factory("train", "data.n_train=1.5")


def test_unknown_system_lists_the_options(cfg_factory):
    with pytest.raises(ConfigCompositionException, match="Could not find 'system/lorenz4'"):
        cfg_factory("train", "system=lorenz4")
