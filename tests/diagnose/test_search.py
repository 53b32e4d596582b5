import pandas as pd
import pytest
import torch

from mpsim.data.io import load_trajectories
from mpsim.diagnose.noise import noise_level
from mpsim.diagnose.search import find_effects
from mpsim.effects import LinearDamping
from mpsim.metrics import valid_prediction_time
from mpsim.models.physics import PhysicsModel
from mpsim.solvers import ODESolver
from mpsim.systems import CoupledPendulums
from tests.helpers import declared_pendulums


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_names_hidden_damping_with_its_coefficient():
    data = CoupledPendulums(effects=[LinearDamping(0.2, target="omega")]).generate(24, seed=0)
    diag = find_effects(declared_pendulums(data), data, n_boot=30)
    (found,) = diag.accepted
    assert found.kind == "LinearDamping" and found.label == "domega/dt: LinearDamping(omega)"
    assert found.coef[0] == pytest.approx(0.2, rel=0.1)
    assert found.effect == {
        "_target_": "mpsim.effects.LinearDamping",
        "target": "omega",
        "coef": found.coef[0],
        "source": "omega",
    }


def test_no_effect_in_clean_data():
    data = CoupledPendulums().generate(24, seed=1)
    diag = find_effects(declared_pendulums(data), data, n_boot=30)
    assert diag.accepted == []


@pytest.mark.slow  # 3–6 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_works_from_a_hand_written_csv(tmp_path):
    # the data file carries no record of the effect: only states, times, nodes and an edge list
    data = CoupledPendulums(effects=[LinearDamping(0.2, target="omega")]).generate(16, seed=2)
    b, t, n, _ = data.x.shape
    rows = [
        {
            "traj": f"run{i}",
            "t": round(float(data.t[k]), 10),
            "node": j,
            "angle": float(data.x[i, k, j, 0]),
            "rate": float(data.x[i, k, j, 1]),
        }
        for i in range(b)
        for k in range(t)
        for j in range(n)
    ]
    pd.DataFrame(rows).to_csv(tmp_path / "lab.csv", index=False)
    pd.DataFrame({"src": [0, 1], "dst": [1, 0]}).to_csv(tmp_path / "lab_edges.csv", index=False)
    loaded = load_trajectories(tmp_path / "lab.csv")
    assert loaded.meta.get("effects") is None and loaded.state_names == ["angle", "rate"]
    diag = find_effects(declared_pendulums(loaded), loaded, n_boot=30)
    (found,) = diag.accepted
    assert found.label == "drate/dt: LinearDamping(rate)" and found.coef[0] == pytest.approx(0.2, rel=0.1)


def test_noise_estimate_and_valid_prediction_time():
    g = torch.Generator().manual_seed(0)
    t = torch.linspace(0, 10, 201, dtype=torch.float64)
    clean = torch.sin(t)[None, :, None, None].expand(8, -1, 3, 1)
    noisy = clean + 0.01 * torch.randn(clean.shape, generator=g, dtype=torch.float64)
    assert noise_level(noisy)[0] == pytest.approx(0.01, rel=0.15)
    assert noise_level(clean)[0] < 1e-4
    pred = clean + 0.1 * t[None, :, None, None]  # normalised error 0.1·t crosses 0.3 at t = 3
    assert valid_prediction_time(pred, clean, torch.ones(1, dtype=torch.float64), t, 0.3) == pytest.approx(
        3.05, abs=0.06
    )


@pytest.mark.slow  # a whole residual-loop run: `pytest -m slow` (.ci/run runs it)
def test_names_a_hidden_drive_and_its_frequency():
    # Lorenz3 driven on x by 20·sin(20 t); the model knows the autonomous equations only (σ, ρ, β learnable)
    from mpsim.effects import PeriodicForcing
    from mpsim.systems import CoupledLorenz

    data = CoupledLorenz(n_nodes=3, effects=[PeriodicForcing(20.0, 20.0, 0.0, target="x")]).generate(
        16, seed=0, horizon=100, burn_in=80
    )
    model = PhysicsModel(
        3,
        system=CoupledLorenz(n_nodes=3),
        learnable=["sigma", "rho", "beta"],
        solver=ODESolver("dopri5", rtol=1e-7, atol=1e-7),
    ).double()
    model.set_normalisation(data.x.reshape(-1, 3).mean(0), data.x.reshape(-1, 3).std(0))
    diag = find_effects(model, data, n_boot=30)
    (found,) = diag.accepted
    assert found.kind == "PeriodicForcing" and found.target == 0
    assert found.effect["omega"] == pytest.approx(20.0, rel=0.05)
    assert found.effect["amplitude"] == pytest.approx(20.0, rel=0.05)  # refit through the integration
