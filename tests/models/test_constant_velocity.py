"""Constant-velocity baseline: exact on free particles (across box faces), untrainable, runs in `mpsim train`."""

from __future__ import annotations

import json

import pytest
import torch

from mpsim.errors import ConfigError
from mpsim.models.constant_velocity import ConstantVelocity
from mpsim.systems.nbody import NBody
from tests.helpers import run_cli


def test_exact_on_free_particles() -> None:
    """G = 0: the simulator's particles fly straight (and wrap around the box); the baseline is the truth."""
    data = NBody(n_particles=30, G=0.0, n_steps=300, box_size=4.0).generate(3, seed=0)
    model = ConstantVelocity()
    with torch.no_grad():
        pred = model.rollout(data.x[:, 0], data.t, data.inputs())
    d = pred - data.x
    d[..., :2] -= 4.0 * torch.round(d[..., :2] / 4.0)
    assert d.abs().max() < 1e-10
    assert (pred[..., :2].abs() <= 2.0).all()  # positions wrapped: speeds up to 1 cross the 4-wide box
    report = model.report()["nbody"]
    assert report["energy_error"]["200"] < 1e-12  # kinetic energy only: conserved exactly
    assert model.describe()["n_params"] == 0


def test_refuses_training() -> None:
    data = NBody(n_particles=4, n_steps=2).generate(1, seed=0)
    with pytest.raises(ConfigError, match="trainer.max_epochs=0"):
        ConstantVelocity().training_loss(data, data.t, None)


@pytest.mark.slow
def test_train_with_zero_epochs_evaluates_the_baseline(tmp_path) -> None:
    args = [
        "train",
        "system=nbody20",
        "model=constant_velocity",
        "trainer.max_epochs=0",
        "trainer.progress=false",
        "data.n_train=1",
        "data.n_val=1",
        "data.n_test=3",
        "eval.plots=false",
    ]
    proc = run_cli(args, tmp_path, check=True)
    assert "energy error |ΔH/H0|" in proc.stdout
    (path,) = list((tmp_path / "outputs" / "train").rglob("summary.json"))
    s = json.loads(path.read_text())
    assert s["epochs_run"] == 0 and s["model"]["n_params"] == 0 and s["test"]["n_diverged"] == 0
    assert 0 < s["test"]["horizons"]["20"]["rmse_raw"] < s["test"]["horizons"]["200"]["rmse_raw"]
    assert s["model"]["nbody"]["data_energy_drift"]["200"] < 1e-4


def test_flags_ill_conditioned_coulomb_energies() -> None:
    """|H0| small against KE + |PE| marks the relative energy error as ill-conditioned (Coulomb, spec §1)."""
    data = NBody(n_particles=12, force="coulomb", n_steps=3).generate(4, seed=0)
    energies, lines = {}, {}
    for flag in (0.0, 1e9):
        model = ConstantVelocity(energy_flag=flag)
        with torch.no_grad():
            model.rollout(data.x[:, 0], data.t, data.inputs())
        energies[flag] = model.report()["nbody"]
        lines[flag] = " ".join(label for label, _ in model.report_lines())
    assert energies[0.0]["n_ill_conditioned"] == 0 and energies[1e9]["n_ill_conditioned"] == 4
    assert energies[0.0]["energy_error_well_conditioned"] == energies[0.0]["energy_error"]
    assert all(v != v for v in energies[1e9]["energy_error_well_conditioned"].values())  # NaN: none left
    assert "ill-conditioned H0" in lines[1e9] and "ill-conditioned H0" not in lines[0.0]
    assert ConstantVelocity().report_lines() == []  # nothing evaluated yet: no energy rows
