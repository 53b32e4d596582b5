"""Ground-truth simulators, one file per family."""

from mpsim.systems.base import System as System
from mpsim.systems.lorenz import CoupledLorenz as CoupledLorenz
from mpsim.systems.nbody import NBody as NBody
from mpsim.systems.pendulum import CoupledPendulums as CoupledPendulums
from mpsim.systems.quadrotor import QuadrotorSwarm as QuadrotorSwarm
