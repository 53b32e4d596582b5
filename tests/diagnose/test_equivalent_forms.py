"""Equivalent forms on the data's support (issue 61, item 2).

On a state that never changes sign, dry friction of that state, −c·tanh(z/ε), is a constant: it cannot be told from
a constant term (Bias), which is the simpler kind. The loop names the constant and says that the two are
indistinguishable there; it never calls a term of a one-signed position friction.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mpsim.data.dataset import Splits
from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.heldout import EFFECTS_NAMED, judge
from mpsim.diagnose.loop import screen
from mpsim.diagnose.params import DiagnoseParams
from mpsim.models.equations import EquationsModel
from tests.diagnose.white_box import nominal_model

K, Z0, C, B = 4.0, 1.0, 0.3, 6.0  # spring, its anchor, damping, and the constant force the model lacks
H, EVERY, STEPS = 0.005, 10, 80  # RK4 step, logged every 10th: dt = 0.05, 4 s records
NOMINAL = {
    "states": ["z", "v"],
    "equations": {"z": "v", "v": "-k*(z - z0) - c*v"},
    "params": {"k": K, "z0": Z0, "c": C},
    "learnable": ["k"],
    "nodes": 1,
}


def hanging_mass(n: int, seed: int) -> Trajectories:
    """z' = v, v' = −k (z − z0) − c v + b: a mass on a spring under a constant force, its position z around
    z0 + b/k = 2.5 and never below 1.3 — stepped by a hand-written RK4 (not mpsim's simulator), vectorised over
    recordings, logged every 10th step."""
    rng = np.random.default_rng(seed)
    y = np.stack([rng.uniform(1.8, 3.2, n), rng.uniform(-1.0, 1.0, n)], axis=1)  # [n, 2]

    def f(y: np.ndarray) -> np.ndarray:  # y: [n, 2]
        return np.stack([y[:, 1], -K * (y[:, 0] - Z0) - C * y[:, 1] + B], axis=1)

    x = np.empty((n, STEPS + 1, 2))
    for s in range(STEPS * EVERY + 1):  # the generator's time loop
        if s % EVERY == 0:
            x[:, s // EVERY] = y
        k1 = f(y)
        k2 = f(y + 0.5 * H * k1)
        k3 = f(y + 0.5 * H * k2)
        k4 = f(y + H * k3)
        y = y + H / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return Trajectories(
        t=torch.arange(STEPS + 1, dtype=torch.float64) * H * EVERY,
        x=torch.as_tensor(x)[:, :, None, :],
        edge_index=torch.zeros(2, 0, dtype=torch.long),
        meta={"state_names": ["z", "v"], "source": "hanging_mass.csv"},
    )


def nominal(train: Trajectories) -> EquationsModel:
    """The spring and damping as the scientist writes them, without the constant force (k learnable)."""
    return nominal_model(NOMINAL, train)


@pytest.mark.slow  # a whole residual-loop run: `pytest -m slow` (.ci/run runs it)
def test_a_constant_force_on_an_always_positive_position_is_named_bias_not_dry_friction():
    data = hanging_mass(20, seed=0)
    assert float(data.x[..., 0].min()) > 1.0  # z never comes near zero, let alone changes sign
    splits = Splits(data.subset(slice(0, 12)), data.subset(slice(12, 14)), data.subset(slice(14, 20)))
    kinds = ["Bias", "DryFriction", "LinearDamping"]
    params = DiagnoseParams(kinds=kinds, n_boot=20, fit_trajectories=6, horizon=40, shooting_iters=15)
    model = nominal(splits.train)
    diag, library = screen(model, splits.train, params, 0)
    assert ("DryFriction", 0) not in [(c.kind, c.source) for c in library]  # z's: not offered as friction
    assert ("DryFriction", 1) in [(c.kind, c.source) for c in library]  # v's: both signs, kept
    (note,) = diag.equivalent_forms
    assert note.startswith("DryFriction(z) not considered: z never changes sign") and "Bias" in note
    assert diag.as_dict()["equivalent_forms"] == [note]
    j = judge(model, diag, library, splits.train, splits.test, params)
    assert j.verdict == EFFECTS_NAMED
    named = [t.label for t in j.named]
    assert "dv/dt: Bias" in named and not any("DryFriction" in label for label in named)
    (bias,) = [t for t in j.named if t.kind == "Bias"]
    assert bias.values["coef"] == pytest.approx(B, rel=0.1)
    assert not any(t.label == "dv/dt: DryFriction(z)" for t in j.trials)
