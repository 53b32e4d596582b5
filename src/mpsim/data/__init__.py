"""Trajectories container, rollout inputs, file IO, dataset cache, splits and normalisation."""

from mpsim.data.trajectories import Inputs as Inputs
from mpsim.data.trajectories import Trajectories as Trajectories
