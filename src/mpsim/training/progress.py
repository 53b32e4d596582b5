"""Where a training run stands: a progress bar on a terminal, log lines (a heartbeat) without one."""

from __future__ import annotations

import logging
import sys
import time
from typing import Any

from tqdm.auto import tqdm


def on_terminal(stream: Any) -> bool:
    """Whether a progress bar on `stream` redraws in place: a terminal, or a notebook (where `tqdm.auto` draws a
    widget); a file, a pipe or a closed stream is not (there each redraw would append a line)."""
    notebook = sys.modules.get("tqdm.notebook")
    if notebook is not None and issubclass(tqdm, notebook.tqdm_notebook):
        return True
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


def epoch_bar(start_epoch: int, max_epochs: int, enabled: bool) -> tqdm:
    """A bar over epochs `start_epoch`..`max_epochs` on stderr, disabled unless `enabled` and stderr redraws in
    place (`on_terminal`)."""
    return tqdm(
        range(start_epoch, max_epochs + 1),
        initial=start_epoch - 1,
        total=max_epochs,
        disable=not enabled or not on_terminal(sys.stderr),  # where tqdm writes
        desc="train",
        unit="epoch",
        dynamic_ncols=True,
        leave=True,
    )


class Heartbeat:
    """Where a run without a progress bar stands: one line on `log` after every epoch that is a multiple of
    `every_epochs`, and one whenever `every_s` seconds of training have passed since the last (0: never, each)."""

    def __init__(
        self, every_epochs: int, every_s: float, start_epoch: int, max_epochs: int, log: logging.Logger
    ) -> None:
        self.every_epochs, self.every_s, self.first, self.max_epochs = every_epochs, every_s, start_epoch, max_epochs
        self.log = log
        self.t_start = self.t_last = time.perf_counter()

    def __call__(self, epoch: int, row: dict, best_val: float, best_epoch: int) -> None:
        now = time.perf_counter()
        on_epoch = bool(self.every_epochs) and epoch % self.every_epochs == 0
        if not on_epoch and not (self.every_s and now - self.t_last >= self.every_s):
            return
        self.t_last = now
        per_epoch = (now - self.t_start) / (epoch - self.first + 1)  # this session's epochs (a resumed run: since then)
        left = per_epoch * (self.max_epochs - epoch)
        self.log.info(
            f"epoch {epoch}/{self.max_epochs}: train loss {row['train_loss']:.4g}, val {row['val_error']:.4g}, "
            f"test {row['test_error']:.4g} (best val {best_val:.4g} at epoch {best_epoch}), lr {row['lr']:.2g}; "
            f"{per_epoch:.3g} s/epoch, about {_duration(left)} left"
        )


def _duration(seconds: float) -> str:
    minutes = round(seconds / 60)
    return f"{minutes // 60} h {minutes % 60:02d} min" if minutes >= 60 else f"{minutes} min"
