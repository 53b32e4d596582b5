"""`mpsim <command> --help` (mpsim.help): the help names only keys the command has, and its examples run as written
as far as composing their config (the command-line part is in tests/test_cli.py)."""

from __future__ import annotations

import shlex

import pytest
from omegaconf import DictConfig, OmegaConf

from mpsim.cli import COMMANDS, CONF_DIR
from mpsim.config import compose_command, register_schemas
from mpsim.help import HELP, config_groups


def test_every_command_has_its_help():
    assert set(HELP) == set(COMMANDS)
    assert all(len(h.examples) == 3 for h in HELP.values())


@pytest.mark.parametrize("command", list(HELP))
def test_the_help_names_only_keys_of_the_command_and_its_examples_compose(command):
    register_schemas()
    required = ["init=x"] if command in ("eval", "diagnose") else []
    cfg = compose_command(command, required, CONF_DIR)
    groups = {g for g, _, _ in config_groups(command, CONF_DIR)}
    for key, _, _ in HELP[command].keys:
        parent, _, leaf = key.rpartition(".")
        node = OmegaConf.select(cfg, parent) if parent else cfg
        assert key in groups or (isinstance(node, DictConfig) and leaf in node), f"mpsim {command}: {key}"
    for example, _ in HELP[command].examples:
        words = shlex.split(example)
        assert words[:2] == ["mpsim", command]
        assert compose_command(command, words[2:], CONF_DIR) is not None, example
