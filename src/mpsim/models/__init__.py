"""Learned and white-box simulators, one file per model."""

from mpsim.models.base import Model as Model
from mpsim.models.mpnode import MPNODE as MPNODE
