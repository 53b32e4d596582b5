import multiprocessing as mp

import pytest
import torch

from mpsim.data.cache import cache_key, cached
from mpsim.data.dataset import DatasetSpec, fit_normalisation, generate, simulate_splits, split_trajectories
from mpsim.data.trajectories import Trajectories
from mpsim.errors import ConfigError, DataError
from mpsim.systems import CoupledLorenz, CoupledPendulums

SPEC = {"_target_": "mpsim.systems.CoupledPendulums", "name": "pendulum2"}


def test_test_split_does_not_depend_on_training_size(tmp_path):
    system = CoupledPendulums()
    small = simulate_splits(system, DatasetSpec(SPEC, 4, 2, 3, seed=0, horizon=5), cache_dir=tmp_path)
    large = simulate_splits(system, DatasetSpec(SPEC, 10, 2, 3, seed=0, horizon=5), cache_dir=tmp_path)
    assert torch.equal(small.test.x, large.test.x)
    # a larger training set extends the smaller one: same initial states; trajectories agree to the solver tolerance
    assert torch.equal(small.train.x[:, 0], large.train.x[:4, 0])
    assert torch.allclose(small.train.x, large.train.x[:4], atol=1e-6)
    assert not torch.equal(small.train.x[:2], small.val.x)  # splits come from different seed streams


def test_normalisation_uses_the_training_split_only():
    system = CoupledLorenz(n_nodes=2)
    splits = simulate_splits(system, DatasetSpec({"n": 2}, 6, 3, 3, seed=1, horizon=20))
    mean, std = fit_normalisation(splits.train)
    flat = splits.train.x.reshape(-1, 3)
    assert torch.allclose(mean, flat.mean(0)) and torch.allclose(std, flat.std(0))
    assert not torch.allclose(mean, splits.test.x.reshape(-1, 3).mean(0))


def test_split_trajectories_fractions_and_error():
    data = CoupledPendulums().generate(10, seed=0, horizon=3)
    s = split_trajectories(data, (0.6, 0.2, 0.2), seed=0)
    assert s.sizes() == {"train": 6, "val": 2, "test": 2}
    ids = torch.cat([s.train.x[:, 0, 0, 0], s.val.x[:, 0, 0, 0], s.test.x[:, 0, 0, 0]])
    assert len(set(ids.tolist())) == 10
    with pytest.raises(DataError, match="at least one each"):
        split_trajectories(data.subset(slice(0, 2)), (0.7, 0.15, 0.15))
    # three trajectories are enough for the default fractions: one each, not a refusal that asks for three
    assert split_trajectories(data.subset(slice(0, 3)), (0.7, 0.15, 0.15)).sizes() == {"train": 1, "val": 1, "test": 1}
    assert split_trajectories(data.subset(slice(0, 4)), (0.7, 0.15, 0.15)).sizes() == {"train": 2, "val": 1, "test": 1}
    # a zero share is refused as a setting (it said "provide at least 3 trajectories" for a file of 10)
    with pytest.raises(ConfigError, match=r"data.split=\[0.8, 0.2, 0.0\] gives the test split no trajectories"):
        split_trajectories(data, (0.8, 0.2, 0.0))
    with pytest.raises(
        ConfigError,
        match="gives the val and test splits no trajectories; this command needs train, val, test with a share > 0",
    ):
        split_trajectories(data, (1.0, 0.0, 0.0))
    assert split_trajectories(data, (1.4, 0.3, 0.3)).sizes() == split_trajectories(data, (0.7, 0.15, 0.15)).sizes()
    # a command that needs only the test split (eval) may give the others no share: every trajectory, or a part
    every = split_trajectories(data, (0.0, 0.0, 1.0), need=("test",))
    assert every.sizes() == {"train": 0, "val": 0, "test": 10} and set(every.test.x[:, 0, 0, 0].tolist()) == set(
        ids.tolist()
    )
    assert split_trajectories(data, (0.0, 0.5, 0.5), need=("test",)).sizes() == {"train": 0, "val": 5, "test": 5}
    with pytest.raises(ConfigError, match="gives the test split no trajectories; this command needs test"):
        split_trajectories(data, (0.5, 0.5, 0.0), need=("test",))


def test_cache_hit_returns_the_stored_data(tmp_path):
    calls = []

    def build():
        calls.append(1)
        return CoupledPendulums().generate(2, seed=0, horizon=3)

    a = cached(tmp_path, {"k": 1}, build)
    b = cached(tmp_path, {"k": 1}, build)
    assert len(calls) == 1 and torch.equal(a.x, b.x)
    cached(tmp_path, {"k": 2}, build)
    assert len(calls) == 2


def test_damaged_cache_entry_is_rebuilt(tmp_path):
    build = lambda: CoupledPendulums().generate(2, seed=0, horizon=3)  # noqa: E731
    cached(tmp_path, {"k": 1}, build)
    (tmp_path / f"{cache_key({'k': 1})}.npz").write_bytes(b"not a zip file")
    assert cached(tmp_path, {"k": 1}, build).x.shape == (2, 4, 2, 2)


def _worker(args):
    cache_dir, marker_dir, i = args
    import pathlib

    def build():
        pathlib.Path(marker_dir, f"built-{i}").touch()
        return CoupledPendulums().generate(16, seed=0, horizon=40)

    return cached(cache_dir, {"shared": True}, build).x.sum().item()


@pytest.mark.slow
@pytest.mark.scaling  # processes started: .ci/run's `-m scaling` step
def test_concurrent_jobs_build_once_and_agree(tmp_path):
    markers = tmp_path / "markers"
    markers.mkdir()
    with mp.get_context("spawn").Pool(2) as pool:  # two jobs race for one entry: the fewest that can collide
        sums = pool.map(_worker, [(str(tmp_path / "cache"), str(markers), i) for i in range(2)], chunksize=1)
    assert len(set(sums)) == 1
    assert len(list(markers.iterdir())) == 1  # the lock made the other job wait and reuse the entry


def test_a_ground_truth_that_cannot_be_simulated_is_one_config_error():
    # real blow-ups: the adaptive solver's step underflows (torchdiffeq asserts), here with two integrators
    spec = DatasetSpec({"name": "lorenz3", "sigma": 1e300}, 2, 1, 1, horizon=5)
    with pytest.raises(ConfigError, match=r"cannot simulate CoupledLorenz.*sigma=1e\+300.*step size underflowed"):
        simulate_splits(CoupledLorenz(sigma=1e300), spec)
    with pytest.raises(ConfigError, match="cannot simulate CoupledPendulums.*check the system's parameters"):
        generate(CoupledPendulums(gravity=1e300), 2, 0, horizon=5)


def test_simulated_nan_states_are_reported_as_the_system_not_as_bad_data():
    class NaNSystem:
        dt, horizon = 0.1, 4

        def generate(self, n, seed, **kwargs):
            x = torch.full((n, 5, 2, 1), float("nan"))
            return Trajectories(t=torch.arange(5) * 0.1, x=x, edge_index=torch.zeros(2, 0, dtype=torch.long))

    with pytest.raises(ConfigError, match="NaN or infinite.*system.*parameters"):
        generate(NaNSystem(), 2, 0)

    class OtherDataError:
        dt, horizon = 0.1, 4

        def generate(self, n, seed, **kwargs):
            raise DataError("the cache file is damaged")

    with pytest.raises(DataError, match="damaged"):  # not every DataError is a blow-up
        generate(OtherDataError(), 2, 0)


def test_a_sampling_step_far_too_long_ends_with_a_message_not_a_hang(monkeypatch):
    import mpsim.systems.base

    monkeypatch.setattr(mpsim.systems.base, "GROUND_TRUTH_MAX_STEPS", 200)  # the real limit fails the same way
    with pytest.raises(ConfigError, match="too many steps for one sampling interval.*data.dt"):
        generate(CoupledPendulums(), 2, 0, dt=50.0, horizon=2)
    assert len(generate(CoupledPendulums(), 2, 0, dt=0.1, horizon=2).x[0]) == 3  # the defaults are far inside it


@pytest.mark.parametrize("case", ["nbody", "quadrotor", "delay"])
def test_a_fixed_step_ground_truth_refuses_a_sampling_step_far_too_long(case):
    # the fixed-step integrators (N-body velocity Verlet, quadrotor RK4 per 100 Hz tick, delay RK4) would take
    # 1e8+ steps per interval for data.dt=1e6: each refuses before its first step, naming the system and its own dt
    from mpsim.effects import DelayedFeedback
    from mpsim.systems import NBody, QuadrotorSwarm

    system, dt = {
        "nbody": (NBody(n_particles=3), 0.01),
        "quadrotor": (QuadrotorSwarm(n_quads=3), 0.05),
        "delay": (CoupledPendulums(effects=[DelayedFeedback(-0.1, delay=0.5, target="omega", source="theta")]), 0.1),
    }[case]
    with pytest.raises(ConfigError, match=rf"cannot simulate {system.name}: .* far too long .*data.dt={dt:g}"):
        generate(system, 2, 0, dt=1e6, horizon=2)
    if case != "quadrotor":  # (its 3-quad flight takes seconds; tests/systems/test_quadrotor.py flies it)
        assert len(generate(system, 2, 0, dt=dt, horizon=2).x[0]) == 3
