"""`Model` holds what every model needs; what only the residual loop reads are optional protocols
(`mpsim.models.capabilities`), and a model without one is handled as one that declares nothing."""

import torch

from mpsim.data.trajectories import Inputs
from mpsim.graphs.topology import chain
from mpsim.models.base import Model
from mpsim.models.capabilities import (
    ExpressesEffects,
    Interpretable,
    LatentState,
    OneStepPredictor,
    one_step,
    one_step_by_rollouts,
)
from mpsim.models.l2s import L2S
from mpsim.models.mpnode import MPNODE
from mpsim.models.smnn_discovery import SMNNDiscovery
from mpsim.solvers.odeint import ODESolver

LOOP_ONLY = (
    "represents",
    "indistinguishable",
    "represents_polynomials",
    "latent_reset",
    "one_step",
    "sensitivities",
    "sensitivity_names",
    "shift_parameters",
)


def test_the_base_class_carries_no_residual_loop_hooks():
    assert not [name for name in LOOP_ONLY if hasattr(Model, name)]


def test_models_declare_their_capabilities():
    mpnode, l2s, smnn = MPNODE(2), L2S(2), SMNNDiscovery(3, degree=3)
    assert isinstance(mpnode, ExpressesEffects) and isinstance(mpnode, LatentState)
    assert isinstance(mpnode, OneStepPredictor) and not isinstance(mpnode, Interpretable)
    assert isinstance(smnn, ExpressesEffects) and isinstance(smnn, Interpretable) and not isinstance(smnn, LatentState)
    assert smnn.represents_polynomials == 3 and smnn.indistinguishable == ()
    assert not any(isinstance(l2s, p) for p in (ExpressesEffects, LatentState, OneStepPredictor, Interpretable))


def test_one_step_falls_back_to_one_rollout_per_step():
    torch.manual_seed(0)
    model = L2S(2).double()
    x = torch.randn(2, 4, 3, 2, dtype=torch.float64)  # [B, T, N, D]
    t = torch.linspace(0.0, 0.3, 4, dtype=torch.float64)
    steps = one_step(model, x, t, Inputs(chain(3)))
    assert steps.shape == (2, 3, 3, 2)
    first = model.rollout(x[:, 1], t[1:3], Inputs(chain(3)))[:, 1]
    torch.testing.assert_close(steps[:, 1], first)


def test_mpnode_one_step_is_its_own():
    torch.manual_seed(0)
    model = MPNODE(2, message_size=0, solver=ODESolver("dopri5", rtol=1e-9, atol=1e-9)).double()
    x = torch.randn(2, 4, 3, 2, dtype=torch.float64)
    t = torch.linspace(0.0, 0.3, 4, dtype=torch.float64)
    # without messages there is no latent state to carry: its own one_step equals one rollout per step
    inputs = Inputs(chain(3))
    torch.testing.assert_close(one_step(model, x, t, inputs), one_step_by_rollouts(model, x, t, inputs))
