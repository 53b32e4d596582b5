"""`python -m mpsim` for `torchrun` in the tests, which also records when each rank's process leaves: an atexit
hook writes time.time() to ``$MPSIM_EXIT_TIMES/rank<RANK>`` (the ranks' own clock, the same machine)."""

from __future__ import annotations

import atexit
import os
import time
from pathlib import Path

from mpsim.__main__ import main


def _record() -> None:
    Path(os.environ["MPSIM_EXIT_TIMES"], f"rank{os.environ['RANK']}").write_text(repr(time.time()))


atexit.register(_record)
main()
