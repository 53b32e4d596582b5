"""Null data measured as the data were (`mpsim.data.measurement`): noise beyond quantisation, the quantum, and
unmeasured states estimated again."""

from __future__ import annotations

import math

import torch

from mpsim.data.latent import estimate_latent
from mpsim.data.measurement import as_measured, quanta
from mpsim.data.trajectories import Trajectories


def _recording(step: float = 0.01) -> tuple[Trajectories, torch.Tensor]:
    """Positions q = sin t quantised to `step` (measured), velocity estimated; and the clean [1, T, 1, 2] (q, v)."""
    t = torch.arange(0, 10, 0.01, dtype=torch.float64)
    clean = torch.stack([torch.sin(t), torch.cos(t)], dim=-1)[None, :, None, :]
    q = torch.round(clean[..., :1] / step) * step
    measured = Trajectories(t=t, x=q, edge_index=torch.zeros(2, 0, dtype=torch.long), meta={"state_names": ["q"]})
    return estimate_latent(measured, {"v": "q"}, states=["q", "v"]), clean


def test_the_null_is_rounded_to_the_datas_quantum_with_no_extra_noise_at_its_rounding_level():
    data, clean = _recording()
    assert math.isclose(quanta(data)[0], 0.01, rel_tol=1e-6)
    sigma = torch.tensor([0.01 / math.sqrt(12), 0.0])  # all of q's noise is its rounding
    x = as_measured(clean, data.t, data, sigma, torch.Generator().manual_seed(0))
    assert torch.allclose(x[..., 0], torch.round(clean[..., 0] / 0.01) * 0.01, atol=1e-9)  # no noise beyond it
    assert torch.allclose(x, data.x)  # the clean twin measured as the data were is the data


def test_unmeasured_states_are_estimated_again_from_the_noisy_measured_ones():
    data, clean = _recording()
    sigma = torch.tensor([0.02, 0.0])
    x = as_measured(clean, data.t, data, sigma, torch.Generator().manual_seed(1))
    assert not torch.allclose(x[..., 1], clean[..., 1])  # v is not the clean velocity
    again = estimate_latent(
        Trajectories(t=data.t, x=x[..., :1], edge_index=data.edge_index, meta={"state_names": ["q"]}),
        {"v": "q"},
        states=["q", "v"],
    )
    assert torch.allclose(x[..., 1], again.x[..., 1])
    assert data.meta["derived_from"] == {"v": "q"}
