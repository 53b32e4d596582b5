"""Shared fixtures: composed configs for the command functions, one torch thread per test.

Helpers (tiny configs, `make_cfg`, `run_mpsim`, `run_cli`) live in `tests/helpers.py`."""

from __future__ import annotations

import os
import signal

import pytest
import torch
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig

from tests.helpers import make_cfg, reset_hydra


@pytest.fixture(autouse=True)
def _one_thread():
    # tiny tensors: one intra-op thread is fastest and keeps tests quiet on a shared 2-core machine
    torch.set_num_threads(1)
    yield


@pytest.fixture(autouse=True)
def _no_leaked_process_state():
    """A test that leaves the working directory, torch's default dtype, the umask, the SIGINT (Ctrl-C) handler or
    Hydra's global state changed fails (and the state is put back, so that later tests do not fail for it)."""
    cwd, dtype, sigint = os.getcwd(), torch.get_default_dtype(), signal.getsignal(signal.SIGINT)
    umask = os.umask(0o022)
    os.umask(umask)
    yield
    leaked = []
    if os.getcwd() != cwd:
        leaked.append(f"cwd {os.getcwd()}")
        os.chdir(cwd)
    if torch.get_default_dtype() != dtype:
        leaked.append(f"default dtype {torch.get_default_dtype()}")
        torch.set_default_dtype(dtype)
    if signal.getsignal(signal.SIGINT) is not sigint:
        leaked.append(f"SIGINT handler {signal.getsignal(signal.SIGINT)!r}")
        signal.signal(signal.SIGINT, sigint)
    now = os.umask(umask)
    if now != umask:
        leaked.append(f"umask {now:o}")
    if GlobalHydra.instance().is_initialized() or HydraConfig.initialized():
        leaked.append("Hydra's global state")
        reset_hydra()
    assert not leaked, f"the test changed process state: {', '.join(leaked)}"


@pytest.fixture
def cfg_factory(tmp_path):
    def factory(command: str, *overrides: str):
        return make_cfg(command, list(overrides), tmp_path)

    return factory
