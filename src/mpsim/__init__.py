"""mpsim: learning modular simulators of coupled dynamical systems."""

from mpsim.data.trajectories import Trajectories as Trajectories
from mpsim.systems.base import System as System

__version__ = "0.1.0"
