"""The loop's rounds: which path a model takes with fix=true, and what the result records."""

import pytest
import torch
from torch import nn

from mpsim.data.dataset import Splits
from mpsim.diagnose.heldout import EFFECTS_NAMED
from mpsim.diagnose.loop import run_loop, white_box
from mpsim.diagnose.params import DiagnoseParams
from mpsim.diagnose.shooting import shooting_fit
from mpsim.effects import LinearDamping
from mpsim.systems import CoupledPendulums
from tests.helpers import declared_pendulums


def _model(train, extra: bool):
    model = declared_pendulums(train)
    if extra:  # a trainable parameter that is neither a named physical one nor an effect's: a network's part
        model.register_parameter("unnamed", nn.Parameter(torch.zeros((), dtype=torch.float64)))
    return model


@pytest.mark.slow  # a whole residual-loop run: `pytest -m slow` (.ci/run runs it)
def test_a_model_with_unnamed_parameters_is_fixed_by_finetuning_against_a_control():
    data = CoupledPendulums(effects=[LinearDamping(0.2, target="omega")]).generate(32, seed=3, horizon=80)
    splits = Splits(data.subset(slice(0, 16)), data.subset(slice(16, 24)), data.subset(slice(24, 32)))
    model = _model(splits.train, extra=True)
    assert not white_box(model) and white_box(_model(splits.train, extra=False))
    tags: list[str] = []

    def finetune(m, tag):
        tags.append(tag)
        shooting_fit(m, splits.train.subset(slice(0, 6)), 20, [p for p in m.parameters() if p.requires_grad], 15)
        return m, f"{tag}/best.ckpt"

    def save(m, k):  # the finetune path hands back the finetune's own checkpoint: nothing is saved separately
        raise AssertionError("save is not used when the fix was finetuned")

    result = run_loop(
        model, splits, DiagnoseParams(n_boot=20, fit_trajectories=6), [1, 10], finetune=finetune, save=save
    )
    assert result.judgement.trials == []  # no frozen-network fits for a black-box model with a finetune at hand
    assert result.verdict == EFFECTS_NAMED and result.exit_code == 0
    assert [t.label for t in result.named] == ["domega/dt: LinearDamping(omega)"]
    assert abs(result.named[0].values["coef"] - 0.2) < 0.01
    assert tags[0] == "round1/control" and result.checkpoint in [f"{t}/best.ckpt" for t in tags[1:]]
    first = result.rounds[0]
    assert first["added"] == ["domega/dt: LinearDamping(omega)"] and first["then"]["named"] == []
    assert result.after is not None and result.after["rollout_rmse"] < 0.1 * result.before["rollout_rmse"]
    assert result.finetuned[0].error_final < 0.1 * result.finetuned[0].error_control
