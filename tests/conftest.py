"""Shared fixtures: composed configs for the command functions, one torch thread per test.

Helpers (tiny configs, `make_cfg`, `run_mpsim`, `run_cli`) live in `tests/helpers.py`."""

from __future__ import annotations

import pytest
import torch

from tests.helpers import make_cfg


@pytest.fixture(autouse=True)
def _one_thread():
    # tiny tensors: one intra-op thread is fastest and keeps tests quiet on a shared 2-core machine
    torch.set_num_threads(1)
    yield


@pytest.fixture
def cfg_factory(tmp_path):
    def factory(command: str, *overrides: str):
        return make_cfg(command, list(overrides), tmp_path)

    return factory
