"""mpsim: learning modular simulators of coupled dynamical systems."""

import os

# Back large CPU tensors (≥ 2 MB) by transparent huge pages. Read by torch's allocator once, so it must be set
# before torch is first imported: a fresh 184 MB tensor then costs ~45 instead of ~90 ms of page faults, which
# makes a long S-MNN solve (T = 5000, 1536 columns: a dozen such tensors per step) ~25 % faster. No effect on
# GPU memory or where the kernel does not offer THP; a value set by the user wins.
os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")

from mpsim.data.trajectories import Trajectories as Trajectories
from mpsim.systems.base import System as System

__version__ = "0.1.0"
