"""`python -m mpsim <command> [overrides]`: the `mpsim` console script, and the entry point for `torchrun`.

`torchrun --nproc_per_node=2 -m mpsim train ...` starts one copy of the command per rank. Rank 0 runs it
exactly as `mpsim train ...` would (its run directory, `.hydra/` record and log); every other rank runs it
without a run directory of its own (Hydra's run directory is the start directory, with no `.hydra/` record
and no log file), so only rank 0 writes files. A resumed run (`resume=`) keeps the directory it resumes on
every rank: the ranks read its `last.ckpt`.
"""

from __future__ import annotations

import os
import sys

FALSE = {"false", "no", "0", "off", "null"}


def worker_args(argv: list[str]) -> list[str]:
    """The command line of this rank: `argv` itself on rank 0 or without `torchrun`; on the other ranks, with
    the Hydra overrides that keep them from writing (no `.hydra/`, no log file, no new run directory)."""
    rank, world = int(os.environ.get("RANK", "0")), int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1 or rank == 0 or not argv:
        return argv
    extra = ["hydra.output_subdir=null", "hydra/job_logging=none"]
    resumes = [a.split("=", 1)[1] for a in argv if a.startswith("resume=")]
    if not any(a.startswith("hydra.run.dir=") for a in argv) and (not resumes or resumes[-1].lower() in FALSE):
        extra.append("hydra.run.dir=.")
    return [*argv, *extra]


def main() -> None:
    from mpsim.cli import main as cli_main

    cli_main(worker_args(sys.argv[1:]))


if __name__ == "__main__":
    main()
