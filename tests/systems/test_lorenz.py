import pytest
import torch

from mpsim.systems import CoupledLorenz
from mpsim.systems.lorenz import lorenz_coupling


@pytest.mark.parametrize("n,c", [(3, 0.01), (10, 5.0)])
def test_coupling_matrix(n, c):
    h = lorenz_coupling(n, c, seed=42)
    assert h.shape == (3 * n, 3 * n)
    blocks = h.reshape(n, 3, n, 3).permute(0, 2, 1, 3)  # [n, n, 3, 3]
    assert torch.all(blocks[torch.arange(n), torch.arange(n)] == 0)  # no self-coupling
    assert torch.linalg.norm(h) == pytest.approx(c, rel=1e-12)
    assert (h >= 0).all()
    assert torch.equal(h, lorenz_coupling(n, c, seed=42))


def test_single_lorenz_is_the_classic_system():
    system = CoupledLorenz(n_nodes=1)
    assert torch.count_nonzero(system.H) == 0
    x = torch.tensor([[[1.0, 2.0, 3.0]]], dtype=torch.float64)
    dx = system.rhs(torch.tensor(0.0), x)[0, 0]
    expected = torch.tensor([10 * (2 - 1), 1 * (28 - 3) - 2, 1 * 2 - 8 / 3 * 3], dtype=torch.float64)
    assert torch.allclose(dx, expected)


def test_coupling_term_is_h_times_the_interleaved_state():
    system = CoupledLorenz(n_nodes=3, coupling=1.0)
    x = torch.randn(4, 3, 3, dtype=torch.float64)
    own = CoupledLorenz(n_nodes=3, coupling=0.0).rhs(torch.tensor(0.0), x)
    coupled = system.rhs(torch.tensor(0.0), x)
    flat = x.reshape(4, 9)
    assert torch.allclose(coupled - own, (flat @ system.H.T).reshape(4, 3, 3))


def test_graph_is_complete_without_self_loops():
    system = CoupledLorenz(n_nodes=4)
    ei = system.edge_index
    assert ei.shape == (2, 12) and not (ei[0] == ei[1]).any()


def test_data_range_and_metadata():
    traj = CoupledLorenz(n_nodes=3).generate(5, seed=0)
    assert traj.x.shape == (5, 51, 3, 3)
    assert traj.x[:, 0].abs().max() <= 1.0
    assert traj.meta["dt"] == pytest.approx(0.05)
    assert len(traj.meta["params"]["H"]) == 9  # the coupling matrix travels with the data


def test_burn_in_discards_the_start_and_keeps_the_clock():
    system = CoupledLorenz(n_nodes=2)
    long = system.generate(3, seed=4, horizon=30)
    late = system.generate(3, seed=4, horizon=10, burn_in=20)
    assert late.x.shape == (3, 11, 2, 3)
    assert torch.allclose(late.t, long.t[20:])
    assert torch.allclose(late.x, long.x[:, 20:], atol=1e-6)
