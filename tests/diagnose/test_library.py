import math

import pytest
import torch

from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.library import build_library, delayed, dominant_frequency, refine_frequency
from mpsim.systems import CoupledPendulums


def test_delayed_shift_keeps_a_constant_history():
    x = torch.arange(5.0).reshape(1, 5, 1, 1)
    assert delayed(x, 2)[0, :, 0, 0].tolist() == [0.0, 0.0, 0.0, 1.0, 2.0]


def test_library_columns_are_step_averaged_basis_functions():
    data = CoupledPendulums().generate(3, seed=0, horizon=6)
    lib = build_library(
        data,
        omegas={1: 2.0},
        delays=[0.2],
        kinds=("LinearDamping", "PeriodicForcing", "DelayedFeedback", "SineCoupling"),
    )
    kinds = [c.kind for c in lib]
    assert kinds.count("LinearDamping") == 2 and kinds.count("PeriodicForcing") == 1
    damping_w = next(c for c in lib if c.kind == "LinearDamping" and c.source == 1)
    w = data.x[..., 1:2]
    assert torch.allclose(damping_w.features, -0.5 * (w[:, 1:] + w[:, :-1]))
    forcing = next(c for c in lib if c.kind == "PeriodicForcing")
    s = torch.sin(2.0 * data.t)
    assert torch.allclose(forcing.features[0, :, 0, 0], 0.5 * (s[1:] + s[:-1]))
    assert next(c for c in lib if c.kind == "DelayedFeedback").params["delay"] == 0.2


def test_periodogram_and_refinement_find_the_drive_frequency():
    t = torch.arange(60, dtype=torch.float64) * 0.05
    omega = 7.3
    g = torch.Generator().manual_seed(0)
    r = 2.0 * torch.sin(omega * t)[None, :, None] + 0.5 * torch.randn(16, 60, 2, generator=g, dtype=torch.float64)
    w0, freqs, power = dominant_frequency(r, t)
    assert abs(w0 - omega) < 2 * math.pi / 3.0  # within a frequency bin of the 3 s record
    w = refine_frequency(r.mean(dim=(0, 2)), t, w0, 2 * math.pi / 3.0)
    assert abs(w - omega) / omega < 0.01


def test_a_drive_with_a_phase_per_recording_is_found_by_the_incoherent_periodogram():
    from mpsim.diagnose.library import PhasedDrive, incoherent_frequency, phased_columns

    g = torch.Generator().manual_seed(0)
    t_mid = torch.linspace(0.025, 9.975, 200, dtype=torch.float64)
    phases = 2 * math.pi * torch.rand(24, generator=g, dtype=torch.float64)
    r = 1.5 * torch.sin(3.1 * t_mid[None, :] + phases[:, None])[..., None].expand(24, 200, 2)
    r = r + 0.3 * torch.randn(r.shape, generator=g, dtype=torch.float64)
    assert incoherent_frequency(r, t_mid) == pytest.approx(3.1, rel=0.01)
    # the average over recordings, which a phase-coherent periodogram sees, keeps a quarter of the drive at most
    assert float(r.mean(dim=(0, 2)).std()) < 0.3 * float(r.std())
    data = Trajectories(
        t=torch.linspace(0, 10, 11, dtype=torch.float64),
        x=torch.zeros(3, 11, 2, 1),
        edge_index=torch.zeros(2, 0, dtype=torch.long),
        meta={"state_names": ["v"]},
    )
    cols = phased_columns(data, 3.1)  # [B, T-1, N, 2B]: recording b's sin/cos only in its own rows
    assert cols.shape == (3, 10, 2, 6) and float(cols[0, :, :, 2:].abs().max()) == 0.0
    drive = PhasedDrive(1.5, 3.1, phases[:3].tolist(), target=0).bind(["v"])
    out = drive.features(torch.tensor(1.0, dtype=torch.float64), torch.zeros(3, 2, 1, dtype=torch.float64), None)
    assert torch.allclose(out[:, 0, 0], torch.sin(3.1 + phases[:3]))


def test_phase_lag_alpha_and_k_from_cos_coefficient_and_the_models_sin_coupling():
    """K·Σ sin(θj − θi − α): the model's sin coupling holds K cos α, the named cos coefficient −K sin α."""
    from mpsim.diagnose.trial import phase_lag
    from mpsim.models.equations import EquationsModel
    from mpsim.systems.equations import EquationsSystem

    alpha, k = 0.25, 0.4
    spec = {
        "name": "ring4",
        "states": ["theta"],
        "equations": {"theta": "w + K*sum_nbr(sin(theta_j - theta))"},
        "params": {"w": [0.9, 1.1, 1.3, 0.7], "K": k * math.cos(alpha)},
        "learnable": ["w", "K"],
        "graph": "ring",
        "init": {"theta": [-3.14159, 3.14159]},
        "dt": 0.1,
        "horizon": 20,
    }
    data = EquationsSystem(spec).generate(4, seed=0)
    model = EquationsModel(1, spec=spec).double()
    vals, interval, note = phase_lag(model, data, 0, -k * math.sin(alpha), 0.001)
    assert abs(vals["alpha"] - alpha) < 1e-6 and abs(vals["K"] - k) < 1e-6
    assert interval["alpha"][0] < alpha < interval["alpha"][1]
    assert "`K`" in note
    # a coupling the model does not hold as one parameter: no α claimed
    spec_w = {**spec, "equations": {"theta": "w"}, "params": {"w": [0.9, 1.1, 1.3, 0.7]}, "learnable": ["w"]}
    assert phase_lag(EquationsModel(1, spec=spec_w).double(), data, 0, -0.1, 0.001) is None


def _two_states(z: torch.Tensor, v: torch.Tensor) -> Trajectories:  # z, v: [B, T] each
    return Trajectories(
        t=torch.arange(z.shape[1], dtype=torch.float64) * 0.05,
        x=torch.stack([z, v], dim=-1)[:, :, None, :],
        edge_index=torch.zeros(2, 0, dtype=torch.long),
        meta={"state_names": ["z", "v"]},
    )


def test_dry_friction_of_a_state_that_never_changes_sign_is_left_to_bias():
    """Issue 61, item 2: on z > 0, −c·tanh(z/ε) is a constant: not offered as friction, and the note says why."""
    t = torch.arange(101, dtype=torch.float64) * 0.05
    phase = torch.linspace(0.0, 3.0, 4, dtype=torch.float64)[:, None]  # [B, 1]
    z = 2.5 + torch.cos(2.0 * t + phase)  # [B, T]: 1.5 … 3.5, always positive
    v = -2.0 * torch.sin(2.0 * t + phase)  # [B, T]: both signs
    notes: list[str] = []
    lib = build_library(_two_states(z, v), kinds=("Bias", "DryFriction"), notes=notes)
    assert [(c.kind, c.source) for c in lib] == [("Bias", None), ("DryFriction", 1)]
    (note,) = notes
    assert note.startswith("DryFriction(z) not considered: z never changes sign on these data")
    assert "min 1.5" in note and "max 3.5" in note and "Bias" in note and "indistinguishable" in note
    # a state with both signs keeps its candidate, and so does one that is positive only where tanh still varies
    # when the caller projects what a model expresses (`one_signed_friction`)
    both = build_library(_two_states(z - 2.5, v), kinds=("DryFriction",), notes=notes)
    assert [c.source for c in both] == [0, 1] and len(notes) == 1
    kept = build_library(_two_states(z, v), kinds=("DryFriction",), one_signed_friction=True)
    assert [c.source for c in kept] == [0, 1]


def test_a_state_positive_but_resolved_near_zero_is_not_friction_either():
    t = torch.arange(201, dtype=torch.float64) * 0.05
    z = 1.0 + torch.cos(t)[None, :].expand(3, -1)  # [B, T]: 0 … 2, touches zero, never below
    v = -torch.sin(t)[None, :].expand(3, -1)
    notes: list[str] = []
    lib = build_library(_two_states(z, v), kinds=("DryFriction",), notes=notes)
    assert [c.source for c in lib] == [1]
    assert "one-sided saturation" in notes[0]  # not a constant here: said so, not "Bias covers it"
