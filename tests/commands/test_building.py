"""`mpsim.commands.building.build`: what instantiating a config node raises becomes one message naming the node."""

import pytest
from omegaconf import OmegaConf

from mpsim.commands.building import build
from mpsim.errors import ConfigError, ResourceError


def test_running_out_of_memory_while_building_is_a_resource_error_not_a_traceback():
    """A MemoryError carries no message: it used to end in an IndexError while the message was composed."""
    node = OmegaConf.create({"_target_": "builtins.bytearray", "_args_": [10**16]})
    with pytest.raises(ResourceError, match=r"building system \(builtins.bytearray\) ran out of memory"):
        build(node, "system")


def test_any_other_failure_names_the_node_and_the_last_line_of_its_cause():
    node = OmegaConf.create({"_target_": "builtins.int", "_args_": ["seven"]})
    with pytest.raises(ConfigError, match=r"cannot build solver \(builtins.int\): invalid literal for int"):
        build(node, "solver")
