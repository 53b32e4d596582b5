"""mpsim: learning modular simulators of coupled dynamical systems.

Importing mpsim changes nothing outside it (no environment variable, no allocator setting, no matplotlib
backend): process-wide settings are made by the command-line entry point (`mpsim.process`)."""

from mpsim.version import __version__

__all__ = ["System", "Trajectories", "__version__"]


def __getattr__(name: str):
    """`mpsim.Trajectories` and `mpsim.System`, imported on first use: `mpsim --help` and config errors answer
    without importing torch, and the entry points set the allocator up before torch is imported
    (`mpsim.process`)."""
    if name == "Trajectories":
        from mpsim.data.trajectories import Trajectories

        return Trajectories
    if name == "System":
        from mpsim.systems.base import System

        return System
    raise AttributeError(f"module 'mpsim' has no attribute {name!r}")
