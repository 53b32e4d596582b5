"""The end of a multirun (`-m`, or a search such as `hparams_search=`): the table of its jobs.

A Hydra callback (`hydra.callbacks.jobs_table` in conf/train.yaml and conf/eval.yaml). Hydra calls it in the
process that started the sweep once every job has finished, whatever launcher ran them (in this process,
joblib's workers, SLURM), so the table covers every job. It prints what `mpsim report runs='[<sweep dir>]'`
prints and writes nothing.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from mpsim.errors import MpsimError


class JobsTable(Callback):
    """Print the report table of a multirun's jobs when the multirun ends."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        from mpsim.report import jobs_table  # pandas: only when a multirun ends

        task = config.get("task", "train")
        sweep = Path(str(config.hydra.sweep.dir))
        if not sweep.is_dir():
            return
        try:
            text = jobs_table(sweep, Path.cwd())
        except MpsimError as err:  # a job's summary that cannot be read: the jobs themselves are done
            print(f"mpsim {task}: warning: no table of the jobs: {err}", file=sys.stderr)
            return
        if text:
            print(f"\n{text}\nThe same table, with other columns or layouts: mpsim report runs='[{sweep}]'")
