import contextlib
import math

import pytest
import torch
from torch import nn

from mpsim.data.dataset import fit_normalisation
from mpsim.errors import ConfigError
from mpsim.models import MPNODE
from mpsim.models.base import Model
from mpsim.solvers import ODESolver
from mpsim.systems import CoupledPendulums
from mpsim.training import Trainer
from mpsim.training.checkpoint import load_checkpoint


def _data():
    system = CoupledPendulums()
    return [system.generate(n, seed=s, horizon=10) for n, s in ((16, 0), (6, 1), (6, 2))]


def _model(train):
    torch.manual_seed(0)
    model = MPNODE(2, solver=ODESolver("rk4"))
    model.set_normalisation(*fit_normalisation(train))
    return model


def _trainer(epochs, **kw):
    return Trainer(
        max_epochs=epochs, batch_size=5, lr=1e-2, plateau_patience=2, early_stop_patience=0, progress=False, **kw
    )


def test_training_reduces_the_validation_error(tmp_path):
    train, val, test = _data()
    model = _model(train)
    trainer = _trainer(8).fit(model, train, val, test, run_dir=tmp_path)
    hist = trainer.history_
    assert [r["epoch"] for r in hist] == list(range(9))  # epoch 0 = the untrained model
    assert trainer.best_val_ < 0.7 * hist[0]["val_error"]
    assert (tmp_path / "checkpoints" / "best.ckpt").is_file() and (tmp_path / "metrics.csv").is_file()
    lines = (tmp_path / "metrics.csv").read_text().splitlines()
    assert lines[0].startswith("epoch,train_loss,val_error,test_error,lr") and len(lines) == 10


def test_resume_gives_the_same_result_as_an_uninterrupted_run(tmp_path):
    train, val, test = _data()
    full = _trainer(6).fit(_model(train), train, val, test, run_dir=tmp_path / "full")
    full_state = load_checkpoint(tmp_path / "full" / "checkpoints" / "last.ckpt")

    _trainer(3).fit(_model(train), train, val, test, run_dir=tmp_path / "part")  # "killed" after epoch 3
    last = load_checkpoint(tmp_path / "part" / "checkpoints" / "last.ckpt")
    model = _model(train)
    resumed = _trainer(6).fit(model, train, val, test, run_dir=tmp_path / "part", resume_state=last["trainer"])

    keys = ("epoch", "train_loss", "val_error", "test_error", "lr")
    rows = lambda h: [[None if r[k] != r[k] else r[k] for k in keys] for r in h]  # noqa: E731 (NaN-safe)
    assert rows(resumed.history_) == rows(full.history_)
    stored = torch.load(tmp_path / "part" / "checkpoints" / "last.ckpt", weights_only=True)["trainer"]
    assert isinstance(stored["history_json"], str) and "history" not in stored  # the rows as one text
    resumed_last = load_checkpoint(tmp_path / "part" / "checkpoints" / "last.ckpt")
    for k, v in full_state["model"]["state_dict"].items():
        assert torch.equal(v, resumed_last["model"]["state_dict"][k]), k
    assert resumed.best_epoch_ == full.best_epoch_


def test_a_resumed_run_trains_on_to_a_raised_budget_but_never_past_an_early_stop(tmp_path):
    """When training stops may change on a resume: more epochs continue the same curve; fewer than the run has
    run are refused; a run that stopped early stays stopped (no extra epoch) unless its patience is raised."""
    train, val, test = _data()
    _trainer(3).fit(_model(train), train, val, test, run_dir=tmp_path)
    state = load_checkpoint(tmp_path / "checkpoints" / "last.ckpt")["trainer"]

    def resume(epochs, patience, changed=None):
        st = {**state, **(changed or {})}
        tr = Trainer(max_epochs=epochs, batch_size=5, lr=1e-2, plateau_patience=2, early_stop_patience=patience)
        return tr.fit(_model(train), train, val, test, run_dir=tmp_path / f"r{epochs}_{patience}", resume_state=st)

    assert [r["epoch"] for r in resume(5, 0).history_] == list(range(6))
    with pytest.raises(ConfigError, match="has already run 3 epochs; trainer.max_epochs=2 is fewer"):
        resume(2, 0)
    stopped = {"since_best": 2, "max_epochs": 10}  # as if it had stopped early at epoch 3 of 10 (patience 2)
    kept = resume(10, 2, stopped)
    assert kept.status_ == "early_stopped" and len(kept.history_) == 4  # no epoch more
    with pytest.raises(ConfigError, match="stopped early at epoch 3 .* Raise trainer.early_stop_patience above 2"):
        resume(20, 2, stopped)
    longer = resume(6, 5, stopped)
    assert longer.status_ == "complete" and [r["epoch"] for r in longer.history_] == list(range(7))


class _Exploding(Model):
    """dx/dt = x·exp(w): with a huge w the rollout overflows."""

    def __init__(self):
        super().__init__(2)
        self.w = nn.Parameter(torch.tensor(3.0))

    def rollout(self, x0, t, inputs):
        return x0[:, None] * torch.exp(torch.exp(self.w) * 30 * t)[None, :, None, None]


def test_divergence_stops_cleanly_and_names_the_batch_and_time(tmp_path):
    train, val, test = _data()
    model = _Exploding()
    trainer = _trainer(3).fit(model, train, val, test, run_dir=tmp_path)
    assert trainer.status_ == "diverged"
    assert "epoch 1, batch 0" in trainer.divergence_ and "first became non-finite at t=" in trainer.divergence_
    assert math.isnan(trainer.history_[0]["val_error"]) or trainer.history_[0]["val_error"] > 1e3
    assert (tmp_path / "checkpoints" / "last.ckpt").is_file()  # what was saved before is kept


def test_early_stopping(tmp_path):
    train, val, test = _data()
    model = _model(train)
    trainer = Trainer(max_epochs=50, batch_size=8, lr=1e-9, early_stop_patience=2, progress=False)
    trainer.fit(model, train, val, test, run_dir=tmp_path)
    assert trainer.status_ == "early_stopped" and len(trainer.history_) < 10


def test_window_training_sees_only_short_windows(tmp_path):
    train, val, test = _data()
    seen = []

    class Spy(MPNODE):
        def training_loss(self, batch, t, loss_fn, delta=1.0):
            seen.append((batch.n_times, float(t[0])))
            return super().training_loss(batch, t, loss_fn, delta)

    torch.manual_seed(0)
    model = Spy(2, solver=ODESolver("rk4"))
    model.set_normalisation(*fit_normalisation(train))
    Trainer(max_epochs=3, batch_size=8, window=3, progress=False).fit(model, train, val, test, run_dir=tmp_path)
    assert {n for n, _ in seen} == {4}  # window of 3 steps = 4 time points
    assert len({start for _, start in seen}) > 1  # starts vary between batches
    # an epoch tiles the record: every batch visits every window of the tiling once
    n_batches = -(-len(train) // 8)
    tiles = (train.n_times - 1) // 3 - 1  # at least this many whole windows fit after any offset
    assert tiles >= 2 and len(seen) >= 3 * n_batches * tiles


def test_without_a_progress_bar_a_heartbeat_line_says_where_the_run_stands(tmp_path, caplog, monkeypatch):
    from mpsim.training import progress

    train, val, test = _data()
    with caplog.at_level("INFO", logger="mpsim.training.trainer"):
        _trainer(3, log_every_s=1e-9).fit(_model(train), train, val, test, run_dir=tmp_path / "quiet")
    beats = [r.getMessage() for r in caplog.records if " s/epoch, about " in r.getMessage()]
    assert [b.split(":")[0] for b in beats] == ["epoch 1/3", "epoch 2/3", "epoch 3/3"]
    assert "(best val " in beats[0] and beats[-1].endswith("about 0 min left")

    caplog.clear()  # every trainer.log_every epochs, whatever the time
    with caplog.at_level("INFO", logger="mpsim.training.trainer"):
        _trainer(5, log_every=2, log_every_s=0).fit(_model(train), train, val, test, run_dir=tmp_path / "epochs")
    beats = [r.getMessage() for r in caplog.records if " s/epoch, about " in r.getMessage()]
    assert [b.split(":")[0] for b in beats] == ["epoch 2/5", "epoch 4/5"]

    caplog.clear()
    monkeypatch.setattr(progress, "on_terminal", lambda stream: True)  # a bar needs a terminal
    with caplog.at_level("INFO", logger="mpsim.training.trainer"):
        _trainer(2, log_every=0, log_every_s=0).fit(_model(train), train, val, test, run_dir=tmp_path / "never")
        Trainer(max_epochs=2, batch_size=5, progress=True, log_every=1, log_every_s=1e-9).fit(
            _model(train), train, val, test, run_dir=tmp_path / "bar"
        )  # the bar already says it
    assert not [r for r in caplog.records if " s/epoch, about " in r.getMessage()]


def test_without_a_terminal_there_is_no_bar_but_a_line_every_log_every_epochs(tmp_path, caplog):
    # output redirected to a file: a bar would write one long line of carriage returns there
    import io

    train, val, test = _data()
    stderr = io.StringIO()  # not a terminal
    trainer = Trainer(max_epochs=4, batch_size=5, progress=True, log_every=2, log_every_s=0)
    with caplog.at_level("INFO", logger="mpsim.training.trainer"), contextlib.redirect_stderr(stderr):
        trainer.fit(_model(train), train, val, test, run_dir=tmp_path)
    assert "\r" not in stderr.getvalue() and "epoch/s" not in stderr.getvalue()
    beats = [r.getMessage() for r in caplog.records if " s/epoch, about " in r.getMessage()]
    assert [b.split(":")[0] for b in beats] == ["epoch 2/4", "epoch 4/4"]


def test_lbfgs_stops_when_an_epoch_moves_no_parameter(tmp_path):
    """A white-box model that cannot fit (its spec lacks the data's damping) converges within an epoch or two;
    full-batch L-BFGS would then repeat the same epoch until early stopping ran out of patience."""
    from mpsim.effects import LinearDamping
    from mpsim.models.equations import EquationsModel
    from mpsim.systems.equations import EquationsSystem

    osc = {"states": ["x", "v"], "equations": {"x": "v", "v": "-k*x"}, "params": {"k": 4.0}, "learnable": ["k"]}
    osc |= {"nodes": 1, "init": {"x": [-1, 1], "v": [-1, 1]}}
    system = EquationsSystem(osc, effects=[LinearDamping(0.4, target="v")])
    train, val = system.generate(6, seed=0, dt=0.1, horizon=40), system.generate(2, seed=1, dt=0.1, horizon=40)
    model = EquationsModel(2, spec={**osc, "params": {"k": 3.0}}, solver=ODESolver("rk4", step_size=0.05)).double()
    model.set_normalisation(*fit_normalisation(train))
    trainer = Trainer(optimizer="lbfgs", lr=1.0, batch_size=64, max_epochs=30, early_stop_patience=20, progress=False)
    trainer.fit(model, train, val, run_dir=tmp_path, checkpoint_base={"model": {}})
    assert trainer.status_ == "early_stopped"
    epochs = [row["epoch"] for row in trainer.history_]
    assert epochs[-1] < 10  # not 20 epochs of patience
    assert trainer.history_[-1]["val_error"] == trainer.history_[-2]["val_error"]  # the last epoch moved nothing
