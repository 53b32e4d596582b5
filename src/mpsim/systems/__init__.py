"""Ground-truth simulators, one file per family."""

from mpsim.systems.base import System as System
from mpsim.systems.lorenz import CoupledLorenz as CoupledLorenz
from mpsim.systems.pendulum import CoupledPendulums as CoupledPendulums
