"""mpsim: learning modular simulators of coupled dynamical systems.

The public API is one list (`__all__`): `System` (true dynamics), `Trajectories` (data), `Model` (learnable
simulators), `Trainer` (fits a model), and the free functions `simulate` (a system's trajectories) and
`rollout` (a model's prediction of them); docs/python.md shows them together.

Importing mpsim changes nothing outside it (no environment variable, no allocator setting, no matplotlib
backend): process-wide settings are made by the command-line entry point (`mpsim.process`). The names are
imported on first use (PEP 562), so `mpsim --help` and config errors answer without importing torch, and the
entry points set the allocator up before torch is imported.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING, Any

from mpsim.version import __version__

if TYPE_CHECKING:
    from mpsim.data.trajectories import Trajectories as Trajectories
    from mpsim.models.base import Model as Model
    from mpsim.models.rollout import rollout as rollout
    from mpsim.systems.base import System as System
    from mpsim.systems.simulation import simulate as simulate
    from mpsim.training.trainer import Trainer as Trainer

#: public name -> the module that defines it
_HOMES = {
    "System": "mpsim.systems.base",
    "Trajectories": "mpsim.data.trajectories",
    "Model": "mpsim.models.base",
    "Trainer": "mpsim.training.trainer",
    "simulate": "mpsim.systems.simulation",
    "rollout": "mpsim.models.rollout",
}

__all__ = ["System", "Trajectories", "Model", "Trainer", "simulate", "rollout", "__version__"]


def __getattr__(name: str) -> Any:
    """The public names, each imported from its module on first use."""
    if name not in _HOMES:
        raise AttributeError(f"module 'mpsim' has no attribute {name!r}")
    value = getattr(import_module(_HOMES[name]), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
