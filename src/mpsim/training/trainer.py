"""`Trainer`: the one stateful object — optimiser, schedule, early stopping, checkpoints, metrics, progress.

Training follows MPNODE.jl: full free-running rollouts from each trajectory's first state (single shooting),
loss on states only, Adam with a global-norm gradient clip, learning rate halved on a plateau of the
validation error. Every epoch ends with a validation and a test rollout, one row in `metrics.csv`, and an
atomic `last.ckpt` that holds everything needed to continue exactly (`resume`).
"""

from __future__ import annotations

import copy
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from mpsim.data.trajectories import Trajectories
from mpsim.errors import ConfigError, DivergenceError
from mpsim.metrics import LOSSES
from mpsim.models.base import Model
from mpsim.models.rollout import rollout, rollout_error
from mpsim.training.checkpoint import history_row, history_text, save_checkpoint
from mpsim.training.distributed import SINGLE, DistContext
from mpsim.training.loggers import CSVLogger
from mpsim.training.progress import Heartbeat, epoch_bar

OPTIMIZERS = ("adam", "lbfgs")

log = logging.getLogger(__name__)

METRIC_COLUMNS = ("epoch", "train_loss", "val_error", "test_error", "lr", "grad_norm", "epoch_time", "wall_time")


@dataclass
class _Fit:
    """What one `Trainer.fit` call works with: the model, its optimiser, schedule and batch-shuffling generator,
    where each epoch's metrics row goes, and where training stands (epochs since the best validation, the wall
    time and the epoch a resumed run continues from)."""

    model: Model
    opt: torch.optim.Optimizer
    sched: torch.optim.lr_scheduler.ReduceLROnPlateau
    shuffle: torch.Generator
    on_epoch: Callable[[dict[str, Any]], None] | None = None
    since_best: int = 0
    wall_before: float = 0.0
    start_epoch: int = 1


def _rollout_error(model: Model, data: Trajectories, batch_size: int, dist: DistContext) -> float:
    """`rollout_error` under several processes (`dist`): each rolls out its part of the trajectories and the parts
    are gathered, so that every rank measures the same error."""
    if not dist.enabled:
        return rollout_error(model, data, batch_size=batch_size)
    part = dist.local_slice(len(data))  # empty on some ranks when there are fewer trajectories than ranks
    if part.stop > part.start:
        pred, _ = rollout(model, data.subset(part), batch_size=batch_size)
    else:
        pred = data.x[:0].to(model.state_mean.dtype)
    return rollout_error(model, data, pred=dist.gather(pred, len(data)))


class Trainer:
    """Fits a `Model` to trajectories by full-rollout single shooting.

    The defaults are CPU-sized and are the ones `mpsim train` uses (`conf/trainer/default.yaml` and the
    `TrainerConf` schema are checked against this signature by `tests/training/test_trainer_defaults.py`);
    the reference's settings are `trainer=paper`.

    Args:
        max_epochs: upper bound on epochs.
        batch_size: trajectories per optimiser step (reference: 128; the last batch may be partial).
        lr: Adam learning rate (reference: 1e-3).
        weight_decay: Adam weight decay.
        clip_norm: global gradient-norm clip (reference: 500).
        loss: ``huber`` (reference: summed over steps and features, mean over node-trajectories) or ``mse``.
        huber_delta: Huber threshold in normalised units.
        plateau_patience: epochs without validation improvement before the learning rate is multiplied
            by `plateau_factor`.
        plateau_factor: learning-rate factor on a plateau (reference: 0.5).
        min_lr: the learning rate is never reduced below this.
        early_stop_patience: stop after this many epochs without validation improvement (0: never).
        window: train on windows of this many steps instead of whole trajectories (null: whole). An epoch
            tiles every trajectory with windows from a random offset and visits each (batch, window) pair once,
            in random order (a batch shares its clock); validation and test still roll out whole trajectories.
            Long chaotic records train better this way (multiple shooting).
        eval_window: measure the per-epoch validation/test errors over the first this-many steps only
            (null: whole trajectories) — for chaotic systems, whose long rollouts decorrelate from any model.
        eval_batch_size: trajectories per batch when evaluating.
        progress: show a progress bar when it writes to a terminal; where stderr is not one (output redirected
            to a file, a batch job) the bar is left out, as with `progress=false`, and the log lines below say
            where the run stands instead.
        log_every_s: without the bar (`progress=false`, as the recipes run, or no terminal), log one line at
            least this often (seconds; 0: never) — epoch, losses, best validation so far, seconds per epoch and
            the time left — so a run of hours shows it is alive, in its train.log as on the terminal.
        optimizer: ``adam`` (neural models) or ``lbfgs`` (quasi-Newton with a strong-Wolfe line search, for the
            few smooth parameters of white-box models such as `model=equations`; use lr 1 and full batches).
        log_every: without the bar, also log that line after every epoch that is a multiple of this (0: never).

    Examples:
        >>> import tempfile, torch
        >>> from mpsim import Trainer, simulate
        >>> from mpsim.data.dataset import fit_normalisation
        >>> from mpsim.models import MPNODE
        >>> from mpsim.systems import CoupledPendulums
        >>> system = CoupledPendulums()
        >>> train, val = simulate(system, 8, seed=0, horizon=5), simulate(system, 4, seed=1, horizon=5)
        >>> _ = torch.manual_seed(0)
        >>> model = MPNODE(state_dim=2, hidden=8)
        >>> model.set_normalisation(*fit_normalisation(train))
        >>> with tempfile.TemporaryDirectory() as run_dir:
        ...     trainer = Trainer(max_epochs=2, batch_size=4, progress=False).fit(model, train, val, run_dir=run_dir)
        >>> trainer.status_, [row["epoch"] for row in trainer.history_]
        ('complete', [0, 1, 2])
    """

    def __init__(
        self,
        max_epochs: int = 100,
        batch_size: int = 32,
        lr: float = 3e-3,
        weight_decay: float = 0.0,
        clip_norm: float = 500.0,
        loss: str = "huber",
        huber_delta: float = 1.0,
        plateau_patience: int = 10,
        plateau_factor: float = 0.5,
        min_lr: float = 1e-6,
        early_stop_patience: int = 30,
        eval_batch_size: int = 512,
        progress: bool = True,
        log_every_s: float = 300.0,
        window: int | None = None,
        eval_window: int | None = None,
        optimizer: str = "adam",
        log_every: int = 10,
    ) -> None:
        if optimizer not in OPTIMIZERS:
            raise ConfigError(f"trainer.optimizer={optimizer!r} is unknown; choose one of {', '.join(OPTIMIZERS)}.")
        self.optimizer = optimizer
        if loss not in LOSSES:
            raise ConfigError(f"trainer.loss={loss!r} is unknown; choose one of {sorted(LOSSES)}.")
        if max_epochs < 0 or batch_size < 1 or lr <= 0:
            raise ConfigError(
                f"need trainer.max_epochs >= 0, trainer.batch_size >= 1 and trainer.lr > 0; got "
                f"{max_epochs}, {batch_size}, {lr}."
            )
        self.max_epochs, self.batch_size, self.lr, self.weight_decay = max_epochs, batch_size, lr, weight_decay
        self.clip_norm, self.loss, self.huber_delta = clip_norm, loss, huber_delta
        self.plateau_patience, self.plateau_factor, self.min_lr = plateau_patience, plateau_factor, min_lr
        self.early_stop_patience, self.eval_batch_size, self.progress = early_stop_patience, eval_batch_size, progress
        if not log_every_s >= 0:
            raise ConfigError(f"trainer.log_every_s must be >= 0 seconds (0: never); got {log_every_s}.")
        if not log_every >= 0:
            raise ConfigError(f"trainer.log_every must be >= 0 epochs (0: never); got {log_every}.")
        self.log_every_s, self.log_every = log_every_s, log_every
        if window is not None and window < 1:
            raise ConfigError(f"trainer.window must be >= 1 step or null; got {window}.")
        self.window, self.eval_window = window, eval_window

    # ---- fitting -------------------------------------------------------------------------------------
    def fit(
        self,
        model: Model,
        train: Trajectories,
        val: Trajectories,
        test: Trajectories | None = None,
        *,
        run_dir: str | Path,
        seed: int = 0,
        checkpoint_base: dict[str, Any] | None = None,
        resume_state: dict[str, Any] | None = None,
        on_epoch: Callable[[dict[str, Any]], None] | None = None,
        dist: DistContext = SINGLE,
    ) -> Trainer:
        """Train `model` in place; afterwards it holds the weights of the best validation epoch.

        Args:
            model: the model (its normalisation buffers already set).
            train, val, test: splits; `test` is only evaluated (for the test-error curve and Table 2 metric).
            run_dir: where `metrics.csv` and `checkpoints/{best,last}.ckpt` go.
            seed: seed of the batch shuffling.
            checkpoint_base: static checkpoint content (model config, system metadata, normalisation).
            resume_state: the ``trainer`` entry of a `last.ckpt` to continue from.
            on_epoch: called with each epoch's metrics row (default: write it to `metrics.csv` in `run_dir`;
                the command layer passes its loggers here).
            dist: this process's place in a data-parallel job (`mpsim.training.distributed`): each global
                batch is split over the processes, gradients are all-reduced, and only rank 0 writes files.

        Sets:
            history_ (list of metric rows), best_epoch_, best_val_, status_ (complete, early_stopped,
            diverged), divergence_ (message or None), best_state_ (weights of the best epoch).
        """
        run_dir = Path(run_dir)
        self._ckpt_dir, self._base, self._dist = run_dir / "checkpoints", dict(checkpoint_base or {}), dist
        self._loss_step = dist.wrap(model)
        train_d = train.to(model.state_mean.device, model.state_mean.dtype)
        run = _Fit(model, *self._optimiser(model), shuffle=torch.Generator().manual_seed(int(seed)))
        self.history_: list[dict[str, Any]] = []
        self._history_json: list[str] = []  # each row of history_ as JSON text, for last.ckpt (`history_text`)
        self.best_val_, self.best_epoch_, self.status_ = math.inf, 0, "complete"
        self.divergence_: str | None = None
        self.best_state_ = copy.deepcopy(model.state_dict())
        if resume_state is not None:
            self._restore(run, resume_state)
        if on_epoch is None and dist.is_main:
            csv_log = CSVLogger()
            csv_log.start(run_dir, {}, self.history_)
            on_epoch = csv_log.log_epoch
        run.on_epoch = on_epoch
        if resume_state is None:
            self._epoch_zero(run, val, test)
        self._train_epochs(run, train_d, val, test)
        model.load_state_dict(self.best_state_)
        return self

    # ---- the steps of `fit` --------------------------------------------------------------------------
    def _optimiser(self, model: Model) -> tuple[torch.optim.Optimizer, torch.optim.lr_scheduler.ReduceLROnPlateau]:
        """The optimiser (`optimizer`) and its learning-rate schedule (halved on a validation plateau)."""
        opt: torch.optim.Optimizer
        if self.optimizer == "lbfgs":  # a few smooth parameters (white-box models): quasi-Newton with line search
            opt = torch.optim.LBFGS(
                model.parameters(), lr=self.lr, max_iter=10, history_size=20, line_search_fn="strong_wolfe"
            )
        else:
            opt = torch.optim.Adam(model.parameters(), lr=self.lr, weight_decay=self.weight_decay)
        sched = torch.optim.lr_scheduler.ReduceLROnPlateau(
            opt, mode="min", factor=self.plateau_factor, patience=self.plateau_patience, min_lr=self.min_lr
        )
        return opt, sched

    def _restore(self, run: _Fit, state: dict[str, Any]) -> None:
        """Continue from a `last.ckpt`'s trainer `state`: weights, optimiser, schedule, shuffling, history, best."""
        run.model.load_state_dict(state["model_state"])
        run.opt.load_state_dict(state["optimizer"])
        run.sched.load_state_dict(state["scheduler"])
        run.shuffle.set_state(state["shuffle_rng"])
        self.history_ = list(state["history"])
        self._history_json = [history_row(row, self._columns()) for row in self.history_]
        self.best_val_, self.best_epoch_ = state["best_val"], state["best_epoch"]
        self.best_state_ = state["best_state"]
        run.since_best = state["since_best"]
        run.wall_before = self.history_[-1]["wall_time"] if self.history_ else 0.0
        run.start_epoch = state["epoch"] + 1
        before = check_resume(state, self.max_epochs, self.early_stop_patience)
        log.info(
            f"resuming after epoch {state['epoch']} (best val {self.best_val_:.4g} at epoch {self.best_epoch_})"
            + (f"; trainer.max_epochs {before} -> {self.max_epochs}" if before != self.max_epochs else "")
        )
        if self.early_stop_patience and run.since_best >= self.early_stop_patience:
            self.status_ = "early_stopped"  # it had stopped: no epoch more (as if it had never been interrupted)
            run.start_epoch = self.max_epochs + 1

    def _epoch_zero(self, run: _Fit, val: Trajectories, test: Trajectories | None) -> None:
        """Epoch 0: the starting point (untrained, or the checkpoint being finetuned), recorded and saved."""
        row = self._evaluate_row(run.model, val, test, 0, math.nan, run.opt, math.nan, 0.0, 0.0)
        self.best_val_ = row["val_error"] if row["val_error"] == row["val_error"] else math.inf
        self._record(row, run.on_epoch)
        self._save_best(run.model)  # epoch 0 is a candidate: best.ckpt exists even if training never beats it
        self._save_last(run.model, run.opt, run.sched, run.shuffle, 0, run.since_best)

    def _train_epochs(self, run: _Fit, train: Trajectories, val: Trajectories, test: Trajectories | None) -> None:
        """Epochs `run.start_epoch`..`max_epochs`, until training diverges or stops early; a bar on a terminal, log
        lines without one."""
        t_start = time.perf_counter()
        bar = epoch_bar(run.start_epoch, self.max_epochs, self.progress and self._dist.is_main)
        quiet = bar.disable and self._dist.is_main  # no bar: log lines say where the run stands
        beat = Heartbeat(
            self.log_every if quiet else 0, self.log_every_s if quiet else 0.0, run.start_epoch, self.max_epochs, log
        )
        for epoch in bar:
            before = [p.detach().clone() for p in run.model.parameters()] if self.optimizer == "lbfgs" else None
            row = self._epoch(run, train, val, test, epoch, t_start)
            if row is None:
                break
            if before is not None and all(map(torch.equal, before, run.model.parameters())):
                self.status_ = "early_stopped"  # L-BFGS converged: every further epoch would repeat this one
                log.info(f"early stop: L-BFGS converged (no parameter moved in epoch {epoch})")
                break
            loss, val_err, test_err = (f"{row[k]:.3g}" for k in ("train_loss", "val_error", "test_error"))
            bar.set_postfix(loss=loss, val=val_err, test=test_err, lr=f"{row['lr']:.1g}")
            beat(epoch, row, self.best_val_, self.best_epoch_)
            if self.early_stop_patience and run.since_best >= self.early_stop_patience:
                self.status_ = "early_stopped"
                log.info(f"early stop: no validation improvement for {run.since_best} epochs")
                break
        bar.close()

    def _epoch(
        self, run: _Fit, train: Trajectories, val: Trajectories, test: Trajectories | None, epoch: int, t_start: float
    ) -> dict[str, Any] | None:
        """One epoch: train, evaluate, keep the best, record the row and save `last.ckpt`; None if it diverged."""
        t0, loss_fn = time.perf_counter(), LOSSES[self.loss]
        try:
            train_loss, grad_norm = self._train_epoch(run.model, train, run.opt, loss_fn, run.shuffle, epoch)
        except DivergenceError as err:
            self.status_, self.divergence_ = "diverged", str(err)
            log.error(str(err))
            return None
        epoch_time = time.perf_counter() - t0
        wall = run.wall_before + time.perf_counter() - t_start
        row = self._evaluate_row(run.model, val, test, epoch, train_loss, run.opt, grad_norm, epoch_time, wall)
        val_err = row["val_error"]
        if val_err == val_err:  # NaN validation error never counts as an improvement
            run.sched.step(val_err)
        if val_err < self.best_val_:
            self.best_val_, self.best_epoch_, run.since_best = val_err, epoch, 0
            self.best_state_ = copy.deepcopy(run.model.state_dict())
            self._save_best(run.model)
        else:
            run.since_best += 1
        self._record(row, run.on_epoch)
        self._save_last(run.model, run.opt, run.sched, run.shuffle, epoch, run.since_best)
        return row

    def _train_epoch(self, model, data, opt, loss_fn, shuffle, epoch) -> tuple[float, float]:
        model.train()
        order = torch.randperm(len(data), generator=shuffle)
        t = data.t.to(data.x)
        batches = list(range(0, len(data), self.batch_size))
        steps: list[tuple[int, int | None]] = [(b, None) for b in batches]
        if self.window and data.n_times - 1 > self.window:
            offset = int(torch.randint(0, self.window, (1,), generator=shuffle))
            starts = list(range(offset, data.n_times - self.window, self.window)) or [0]
            steps = [(b, s) for b in batches for s in starts]
            steps = [steps[i] for i in torch.randperm(len(steps), generator=shuffle).tolist()]
        total, norms, count = 0.0, [], 0
        for k, (first, wstart) in enumerate(steps):
            # under several processes each takes its part of the global batch (`DistContext.shard`)
            idx, weight = self._dist.shard(order[first : first + self.batch_size])
            batch = data.subset(idx.to(data.x.device))
            bt = t
            if wstart is not None:
                assert self.window is not None  # windows are only drawn when it is set
                batch = batch.time_slice(wstart, wstart + self.window + 1)
                bt = t[wstart : wstart + self.window + 1]
            loss, pred = self._loss_step(batch, bt, loss_fn, self.huber_delta)
            n_local = len(idx) if weight > 0 else 0
            # one sum over the ranks: the batch loss, and a NaN/inf on any rank stops every rank together
            loss_sum, n_sum = self._dist.all_sum([float(loss.detach()) * n_local if n_local else 0.0, n_local])
            if not math.isfinite(loss_sum):
                raise DivergenceError(_divergence_message(pred, bt, epoch, k, idx))
            opt.zero_grad(set_to_none=True)
            (loss if weight == 1.0 else loss * weight).backward()
            clip = self.clip_norm if self.clip_norm and self.clip_norm > 0 else math.inf
            gnorm = torch.nn.utils.clip_grad_norm_(model.parameters(), clip)
            if not torch.isfinite(gnorm):
                raise DivergenceError(
                    f"epoch {epoch}, batch {k}: the gradient became {float(gnorm)} (trajectories "
                    f"{_ids(idx)}). Lower trainer.lr or trainer.clip_norm."
                )
            if isinstance(opt, torch.optim.LBFGS):
                opt.step(self._closure(loss, batch, bt, loss_fn, weight, opt))
            else:
                opt.step()
            model.after_step()
            total += loss_sum
            count += int(n_sum)
            norms.append(float(gnorm))
        return total / max(count, 1), sum(norms) / max(len(norms), 1)

    def _closure(self, loss, batch, t, loss_fn, weight, opt):
        """LBFGS re-evaluates the loss along its line search; its first call reuses the loss (and gradient)
        just computed. Under several processes it returns the global batch loss (the weighted sum over ranks),
        so every rank's line search takes the same step."""
        first = [True]

        def global_loss(value: torch.Tensor) -> torch.Tensor:
            (total,) = self._dist.all_sum([float(value.detach()) * weight])
            return value.new_tensor(total).detach()

        def closure() -> torch.Tensor:
            if first[0]:
                first[0] = False
                return global_loss(loss)
            opt.zero_grad(set_to_none=True)
            value, _ = self._loss_step(batch, t, loss_fn, self.huber_delta)
            (value if weight == 1.0 else value * weight).backward()
            return global_loss(value)

        return closure

    def _evaluate_row(self, model, val, test, epoch, train_loss, opt, grad_norm, epoch_time, wall) -> dict:
        model.eval()
        if self.eval_window:
            val = val.time_slice(0, self.eval_window + 1)
            test = None if test is None else test.time_slice(0, self.eval_window + 1)
        val_err = _rollout_error(model, val, self.eval_batch_size, self._dist)
        test_err = _rollout_error(model, test, self.eval_batch_size, self._dist) if test is not None else math.nan
        return {
            "epoch": epoch,
            "train_loss": train_loss,
            "val_error": val_err,
            "test_error": test_err,
            "lr": opt.param_groups[0]["lr"],
            "grad_norm": grad_norm,
            "epoch_time": epoch_time,
            "wall_time": wall,
        }

    # ---- records -------------------------------------------------------------------------------------
    def _record(self, row: dict[str, Any], on_epoch) -> None:
        self.history_.append(row)
        self._history_json.append(history_row(row, self._columns()))
        if on_epoch is not None:
            on_epoch(row)

    def _columns(self) -> list[str]:
        """The metric names of the history's rows (the first row's keys)."""
        return list(self.history_[0]) if self.history_ else []

    def _payload(self, model: Model, **extra: Any) -> dict[str, Any]:
        """A complete checkpoint: the static base plus the model's current weights and normalisation."""
        return {
            **self._base,
            "model": {
                "state_dim": model.state_dim,
                "control_dim": model.control_dim,
                **self._base.get("model", {}),
                "state_dict": model.state_dict(),
            },
            "normalisation": {
                "mean": model.state_mean.detach().cpu().clone(),
                "std": model.state_std.detach().cpu().clone(),
            },
            "system": self._base.get("system", {}),
            **extra,
        }

    def _save_best(self, model: Model) -> None:
        if not self._dist.is_main:
            return
        metrics = {"epoch": self.best_epoch_, "val_error": self.best_val_}
        save_checkpoint(self._ckpt_dir / "best.ckpt", self._payload(model, metrics=metrics))

    def _save_last(self, model, opt, sched, shuffle, epoch, since_best) -> None:
        if not self._dist.is_main:
            return
        state = {
            "epoch": epoch,
            "model_state": model.state_dict(),
            "optimizer": opt.state_dict(),
            "scheduler": sched.state_dict(),
            "shuffle_rng": shuffle.get_state(),
            "history_json": history_text(self._columns(), self._history_json),
            "best_val": self.best_val_,
            "best_epoch": self.best_epoch_,
            "best_state": self.best_state_,
            "since_best": since_best,
            "max_epochs": self.max_epochs,
        }
        save_checkpoint(self._ckpt_dir / "last.ckpt", self._payload(model, metrics={"epoch": epoch}, trainer=state))


def check_resume(state: dict[str, Any], max_epochs: int, patience: int) -> int:
    """Refuse a resumed budget that cannot be met: fewer epochs than the run in `state` (a last.ckpt's trainer
    state) has run, or more epochs for a run that stopped early (its patience spent, it would stop again at once)
    without raising its patience. Returns the budget the run ran under (`max_epochs` for older checkpoints).

    Raises:
        ConfigError: naming the budget that would work.
    """
    done, since_best = state["epoch"], state["since_best"]
    before = state.get("max_epochs", max_epochs)  # the budget it ran under
    if max_epochs < done:
        raise ConfigError(
            f"resume: the run has already run {done} epochs; trainer.max_epochs={max_epochs} is fewer. "
            f"Give trainer.max_epochs >= {done} (the run was set to {before})."
        )
    if patience and since_best >= patience and max_epochs > max(done, before):
        raise ConfigError(
            f"resume: the run stopped early at epoch {done} (no validation improvement for {since_best} "
            f"epochs, trainer.early_stop_patience={patience}), so trainer.max_epochs={max_epochs} would not train "
            f"it further. Raise trainer.early_stop_patience above {since_best} (0: never stop early) to continue it."
        )
    return before


def _ids(idx: torch.Tensor, limit: int = 8) -> str:
    ids = [int(i) for i in idx[:limit]]
    return f"{ids}{' ...' if len(idx) > limit else ''}"


def _divergence_message(pred: torch.Tensor, t: torch.Tensor, epoch: int, batch: int, idx: torch.Tensor) -> str:
    """Name the batch, the first trajectory and the first time at which the rollout went non-finite."""
    bad = ~torch.isfinite(pred.detach()).flatten(2).all(dim=-1)  # [B, T]
    if bad.any():
        b, k = (int(v) for v in torch.nonzero(bad)[0])
        where = f"trajectory {int(idx[b])} first became non-finite at t={float(t[k]):.4g} (step {k})"
    else:
        where = "the loss overflowed although every prediction is finite"
    return (
        f"training diverged in epoch {epoch}, batch {batch} (trajectories {_ids(idx)}): {where}. "
        "Lower trainer.lr, tighten trainer.clip_norm or use a shorter data.horizon."
    )
