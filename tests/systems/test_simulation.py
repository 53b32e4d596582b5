import pytest
import torch

from mpsim import simulate
from mpsim.data.io import load_npz
from mpsim.errors import ConfigError
from mpsim.systems import CoupledLorenz, CoupledPendulums
from tests.helpers import run_mpsim_ok


def test_simulate_gives_what_mpsim_simulate_writes(tmp_path):
    run_mpsim_ok(
        ["simulate", "system=pendulum2", "n=3", "data.seed=5", "data.horizon=6", f"hydra.run.dir={tmp_path / 'run'}"],
        tmp_path,
    )
    written = load_npz(tmp_path / "run" / "trajectories.npz")
    data = simulate(CoupledPendulums(), 3, seed=5, horizon=6)  # conf/system/pendulum2.yaml is the default
    assert torch.equal(data.t, written.t) and torch.equal(data.x, written.x)
    assert not torch.equal(simulate(CoupledPendulums(), 3, seed=6, horizon=6).x, data.x)  # the seed draws


def test_simulate_passes_the_sampling_options_to_the_system():
    system = CoupledLorenz(n_nodes=1)
    data = simulate(system, 2, seed=1, dt=0.02, horizon=4, burn_in=3)
    assert data.n_times == 5 and torch.allclose(data.t, 0.02 * torch.arange(3, 8, dtype=torch.float64))
    assert torch.equal(data.x, system.generate(2, 1, dt=0.02, horizon=4, burn_in=3).x)
    default = simulate(system, 1)
    assert default.n_times == system.horizon + 1 and default.meta["dt"] == pytest.approx(system.dt)


def test_simulate_reports_bad_sizes_as_a_config_error():
    with pytest.raises(ConfigError, match="n >= 1"):
        simulate(CoupledPendulums(), 0)
