"""A drive with a phase per recording on a chaotic system (issue 61, item 4).

Case (k) of the scorecard (`examples/diagnose_cases/k_chaos_drive_*.yaml`): a Rössler oscillator sped up tenfold
(largest Lyapunov exponent about 0.7 per unit time) with a hidden drive 4·sin(7 t + φ_b) on y, a random phase φ_b
per recording, and measurement noise. Even the exact model tracks such data only for a while, so held-out
windows longer than that saturate for every model, the right one included, and the drive was rejected although
it was found to 0.1 %. The held-out horizon must come from the null twin's own error growth (how long the refit
model tracks its own noisy simulation), and each held-out recording's phase from a warm-up window.
"""

from __future__ import annotations

import functools
from pathlib import Path

import pytest
import torch

from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.heldout import EFFECTS_NAMED, _null_twin, judge
from mpsim.diagnose.loop import screen
from mpsim.diagnose.params import DiagnoseParams
from mpsim.diagnose.shooting import horizon_from_data, null_data
from mpsim.effects import PeriodicForcing
from mpsim.models.equations import EquationsModel
from mpsim.spec import load_spec_file
from mpsim.systems.equations import EquationsSystem
from tests.diagnose.white_box import nominal_model

CASES = Path(__file__).resolve().parents[2] / "examples" / "diagnose_cases"
AMPLITUDE, OMEGA = 4.0, 7.0  # the hidden drive on y (a random phase per recording)
SIGMA = 0.02  # measurement noise, in units of each state's standard deviation
LONG = 150  # a held-out horizon longer than anything tracks these data (3 s, about 2 Lyapunov times)
PARAMS = {"kinds": ["PeriodicForcing"], "targets": ["y"], "n_boot": 10, "fit_trajectories": 6, "shooting_iters": 15}


@functools.cache
def roessler(drive: bool) -> tuple[Trajectories, Trajectories]:
    """(held-in, held-out) recordings of case (k): 200 steps of dt 0.02 each, noisy."""
    effects = [PeriodicForcing(AMPLITUDE, OMEGA, 0.0, target="y", random_phase=True, phase_seed=0)] if drive else []
    data = EquationsSystem(load_spec_file(CASES / "k_chaos_drive_data.yaml"), effects=effects).generate(
        20, seed=0, horizon=200
    )
    std = data.x.reshape(-1, data.state_dim).std(0)  # [D]
    gen = torch.Generator().manual_seed(3)
    data.x = data.x.double() + SIGMA * std * torch.randn(data.x.shape, generator=gen, dtype=torch.float64)
    return data.subset(slice(0, 12)), data.subset(slice(12, 20))


def nominal(train: Trajectories) -> EquationsModel:
    """The undriven oscillator (case (k)'s model spec), float64, normalised on `train`."""
    spec = {k: v for k, v in load_spec_file(CASES / "k_chaos_drive_model.yaml").items() if k != "name"}
    return nominal_model(spec, train)


@pytest.mark.slow  # a whole residual-loop run: `pytest -m slow` (.ci/run runs it)
def test_the_heldout_horizon_is_the_null_twins_tracking_time():
    train, _ = roessler(drive=False)
    model = nominal(train)
    noise = SIGMA * train.x.reshape(-1, train.state_dim).std(0)  # [D]
    params = DiagnoseParams(**PARAMS)
    horizon, null = _null_twin(model, train, noise, LONG, params, 11)
    assert 10 < horizon < LONG  # the exact model loses its own noisy data within LONG steps
    assert null.n_times == horizon + 1  # the null records are cut to the new horizon
    # at the new horizon the null windows' error has just passed a third of the valid-prediction threshold
    longer = null_data(model, train, noise, 11, segment=LONG)
    assert horizon_from_data(model, longer, params.vpt_threshold / 3, above_first=2.0) == horizon
    # a horizon set by hand is kept, and a horizon the model tracks is not changed
    assert _null_twin(model, train, noise, LONG, DiagnoseParams(**PARAMS, horizon=LONG), 11)[0] == LONG
    assert _null_twin(model, train, noise, horizon // 2, params, 11)[0] == horizon // 2


@pytest.mark.slow
def test_a_drive_with_a_phase_per_recording_is_named_on_a_chaotic_system():
    """The screen's windows are too long here (`LONG`, as from records that start where the system is slow);
    with them even the true drive saturates. Cut to the null twin's tracking time, it is named."""
    train, test = roessler(drive=True)
    model = nominal(train)
    params = DiagnoseParams(**PARAMS)
    diag, library = screen(model, train, params, 0)
    diag.horizon = LONG
    j = judge(model, diag, library, train, test, params)
    assert j.verdict == EFFECTS_NAMED, (j.verdict, j.horizon, [(t.label, t.reason) for t in j.trials])
    (drive,) = j.named
    assert drive.kind == "PeriodicForcing" and "phases" in drive.effect  # one phase per recording
    assert drive.values["omega"] == pytest.approx(OMEGA, rel=0.03)
    assert drive.values["amplitude"] == pytest.approx(AMPLITUDE, rel=0.10)
    assert j.horizon < LONG
