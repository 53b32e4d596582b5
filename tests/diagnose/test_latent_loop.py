"""The residual loop on a latent row (issue 60, item 4): Coulomb friction on v when only q is measured.

A driven mass (`tests/diagnose/latent_case.py`: q' = v, v' = (u − c·v − Fc·tanh(v/ε))/m, a multisine force held
between samples, RK4 at 1/20 of the sample step, q quantised at 1 µm with 2 µm noise, 1 s segments); the nominal
model lacks Fc. v is estimated from q (a Savitzky–Golay derivative); the screen regresses the one-step residual
of that estimated trajectory, and the held-out judgement fits every window's velocity start (`diagnose.latent`).
"""

from __future__ import annotations

import pytest

from mpsim.data.dataset import Splits
from mpsim.diagnose.heldout import EFFECTS_NAMED, NOTHING_MISSING
from mpsim.diagnose.loop import run_loop
from mpsim.diagnose.params import DiagnoseParams
from mpsim.diagnose.report import feature_plots
from tests.diagnose.latent_case import COULOMB, MASS, measured, nominal_model


def _run(coulomb: float, with_splits: bool = False):
    data = measured(32, coulomb, seed=0)
    splits = Splits(data.subset(slice(0, 20)), data.subset(slice(20, 22)), data.subset(slice(22, 32)))
    params = DiagnoseParams(n_boot=20, fit_trajectories=10)
    model = nominal_model(splits.train)
    result = run_loop(model, splits, params, [10, 50, 100])
    return (result, model, splits) if with_splits else result


@pytest.mark.slow
def test_dry_friction_on_the_unmeasured_velocity_is_named(tmp_path):
    result, model, splits = _run(COULOMB, with_splits=True)
    assert result.verdict == EFFECTS_NAMED
    (named,) = result.named
    assert named.label == "dv/dt: DryFriction(v)"
    assert named.values["coef"] == pytest.approx(COULOMB / MASS, rel=0.1)
    j = result.judgement
    assert j.error_final < 0.01 * j.error_refit  # held-out multi-step MSE on q
    assert j.measured["observed"] == ["q"] and "Savitzky–Golay" in j.measured["estimated"]["v"]
    assert any("measured states ['q']" in note for note in j.notes)
    # issue 71, item 8: the residual against the named effect's own feature (v: a sign change), as a picture
    (figure,) = feature_plots(result, splits.test, tmp_path)
    assert figure == tmp_path / "plots" / "effect_1.png" and figure.read_bytes()[:4] == b"\x89PNG"


@pytest.mark.slow
def test_the_clean_twin_has_nothing_missing():
    result = _run(0.0)
    assert result.verdict == NOTHING_MISSING and result.named == []
