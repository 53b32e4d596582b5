"""Trajectories container, file IO, dataset cache, splits and normalisation."""

from mpsim.data.trajectories import Trajectories as Trajectories
