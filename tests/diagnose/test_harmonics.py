"""Higher harmonics of phase coupling (issue 61, item 6): sin/cos(k(θ_j − θ_i)), k = 2, 3, in the library.

The visible case: phase oscillators on a ring with a second harmonic in their coupling,
dθ_i/dt = ω_i + K1 Σ_j sin(θ_j − θ_i) + K2 Σ_j sin(2(θ_j − θ_i)), stepped by a hand-written RK4 loop (not mpsim's
simulator); the nominal model is plain Kuramoto coupling (`model=equations`, ω_i and K1 learnable), without K2.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mpsim.data.dataset import Splits
from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.findings import Diagnosis, Finding
from mpsim.diagnose.heldout import EFFECTS_NAMED, _ranked, judge
from mpsim.diagnose.library import build_library
from mpsim.diagnose.loop import screen
from mpsim.diagnose.params import DiagnoseParams
from mpsim.effects import CosineCoupling, EffectContext, SineCoupling
from mpsim.errors import ConfigError
from mpsim.graphs.topology import chain, ring
from mpsim.models.equations import EquationsModel
from tests.diagnose.white_box import nominal_model

W = [0.9, 1.1, 1.3, 0.7, 1.0, 1.2]  # natural frequencies, one per node of the ring
K1, K2 = 0.4, 0.25  # first and second harmonic of the coupling; the nominal model lacks K2
DT, SUB, STEPS = 0.1, 10, 150  # sampling step, RK4 steps per sample, samples per record
NOMINAL = {
    "states": ["theta"],
    "equations": {"theta": "w + K*sum_nbr(sin(theta_j - theta))"},
    "params": {"w": W, "K": K1},
    "learnable": ["w", "K"],
}


def oscillators(n: int, seed: int, k2: float) -> Trajectories:
    """n records of the ring dθ_i/dt = ω_i + K1 Σ_j sin(θ_j − θ_i) + k2 Σ_j sin(2(θ_j − θ_i)) from uniform random
    phases, by classical RK4 at DT/SUB (numpy, vectorised over records and nodes)."""
    rng = np.random.default_rng(seed)
    w = np.asarray(W)  # [N]

    def rhs(th: np.ndarray) -> np.ndarray:  # th: [n, N] phases
        diff = np.stack([np.roll(th, 1, axis=1), np.roll(th, -1, axis=1)], axis=-1) - th[..., None]  # [n, N, 2]
        return w + K1 * np.sin(diff).sum(-1) + k2 * np.sin(2 * diff).sum(-1)

    th = rng.uniform(-math.pi, math.pi, (n, len(W)))  # [n, N]
    x = np.empty((n, STEPS + 1, len(W)))
    h = DT / SUB
    for s in range(STEPS * SUB + 1):  # the generator's time loop
        if s % SUB == 0:
            x[:, s // SUB] = th
        a = rhs(th)
        b = rhs(th + 0.5 * h * a)
        c = rhs(th + 0.5 * h * b)
        d = rhs(th + h * c)
        th = th + h / 6 * (a + 2 * b + 2 * c + d)
    return Trajectories(
        t=torch.arange(STEPS + 1, dtype=torch.float64) * DT,
        x=torch.as_tensor(x)[..., None],
        edge_index=ring(len(W)),
        meta={"state_names": ["theta"], "source": "oscillators.csv"},
    )


def nominal(train: Trajectories) -> EquationsModel:
    """Plain Kuramoto coupling as the scientist writes it (ω_i, K learnable), float64, normalised on `train`."""
    return nominal_model(NOMINAL, train)


def _judge(k2: float):
    data = oscillators(24, seed=0, k2=k2)
    splits = Splits(data.subset(slice(0, 14)), data.subset(slice(14, 16)), data.subset(slice(16, 24)))
    params = DiagnoseParams(n_boot=20, fit_trajectories=6, horizon=40, shooting_iters=15)
    model = nominal(splits.train)
    diag, library = screen(model, splits.train, params, 0)
    return diag, judge(model, diag, library, splits.train, splits.test, params)


def _finding(label: str, share: float, selected: bool) -> Finding:
    return Finding(
        target=0, label=label, kind=label.split(": ")[1].split("(")[0], coef=[0.1], interval=[], gain=share,
        explained_rms=share, alone=share, inclusion=1.0, threshold=0.0, accepted=selected, reason="", effect={},
        selected=selected,
    )  # fmt: skip


@pytest.mark.slow  # a whole residual-loop run: `pytest -m slow` (.ci/run runs it)
def test_second_harmonic_of_the_coupling_is_named():
    diag, j = _judge(K2)
    assert j.verdict == EFFECTS_NAMED
    (named,) = j.named
    assert named.label == "dtheta/dt: SineCoupling(theta, k=2)"
    assert named.kind == "SineCoupling" and named.effect["harmonic"] == 2
    assert named.values["coef"] == pytest.approx(K2, rel=0.1)


def test_clean_ring_names_nothing():
    _, j = _judge(0.0)
    assert j.verdict != EFFECTS_NAMED and not j.named


def test_the_harmonic_term_matches_its_formula():
    x = torch.tensor([[[0.5], [1.0], [-1.0]]], dtype=torch.float64)  # [1, 3, 1] on a chain 0-1-2
    ctx = EffectContext.for_batch(chain(3), x)
    th = x[0, :, 0].tolist()
    sin2 = SineCoupling(0.3, target="theta", harmonic=2).bind(["theta"])(0.0, x, ctx)[0, :, 0]
    expected = [
        0.3 * math.sin(2 * (th[1] - th[0])),
        0.3 * (math.sin(2 * (th[0] - th[1])) + math.sin(2 * (th[2] - th[1]))),
        0.3 * math.sin(2 * (th[1] - th[2])),
    ]
    assert torch.allclose(sin2, torch.tensor(expected, dtype=torch.float64))
    cos3 = CosineCoupling(-0.2, target="theta", harmonic=3).bind(["theta"])(0.0, x, ctx)[0, :, 0]
    assert float(cos3[0].detach()) == pytest.approx(-0.2 * math.cos(3 * (th[1] - th[0])))


def test_harmonic_names_configs_and_refusals():
    plain = SineCoupling(0.3, target="theta").bind(["theta"])
    assert plain.name == "SineCoupling" and "harmonic" not in plain.config()  # k = 1 writes what it always did
    assert plain.describe() == "dtheta/dt += +0.3·Σ_j sin(theta_j − theta_i)"
    second = SineCoupling(0.3, target="theta", harmonic=2).bind(["theta"])
    assert second.name == "SineCoupling(k=2)"
    assert second.describe() == "dtheta/dt += +0.3·Σ_j sin(2·(theta_j − theta_i))"
    cfg = second.config()
    assert cfg["harmonic"] == 2
    again = SineCoupling(**{k: v for k, v in cfg.items() if k != "_target_"})
    assert again.harmonic == 2 and again.config() == cfg  # round trip (fix=true checkpoints keep it)
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(ConfigError, match="harmonic must be an integer >= 1"):
            CosineCoupling(0.1, harmonic=bad)


def test_library_offers_the_harmonics_and_each_counts_as_its_own_kind():
    data = oscillators(3, seed=1, k2=K2)
    lib = build_library(data, kinds=("SineCoupling", "CosineCoupling"))
    labels = [c.label(["theta"]) for c in lib]
    assert labels == [
        "SineCoupling(theta)",
        "SineCoupling(theta, k=2)",
        "SineCoupling(theta, k=3)",
        "CosineCoupling(theta)",
        "CosineCoupling(theta, k=2)",
        "CosineCoupling(theta, k=3)",
    ]
    th = data.x[..., 0]  # [B, T, N]
    diff = torch.stack([th.roll(1, dims=2), th.roll(-1, dims=2)], dim=-1) - th[..., None]  # [B, T, N, 2]
    value = torch.sin(2 * diff).sum(-1)  # [B, T, N]
    assert torch.allclose(lib[1].features[..., 0], 0.5 * (value[:, 1:] + value[:, :-1]))
    assert lib[0].params == {} and lib[1].params == {"harmonic": 2}  # k = 1: the candidate of before
    cfg = lib[2].effect_config([0.1], 0, ["theta"])
    assert cfg["harmonic"] == 3 and lib[2].make_effect([0.1], 0, ["theta"]).harmonic == 3
    assert [c.complexity for c in lib[:3]] == sorted(c.complexity for c in lib[:3]) and lib[0].complexity == 1
    from mpsim.diagnose.params import complexity

    assert complexity("SineCoupling", 3) < complexity("PeriodicForcing")
    # the held-out stage takes one candidate per (kind, harmonic, row): the second harmonic is not crowded out
    findings = [
        _finding("dtheta/dt: SineCoupling(theta)", 0.5, True),
        _finding("dtheta/dt: SineCoupling(theta, k=2)", 0.4, False),
        _finding("dtheta/dt: SineCoupling(theta, k=3)", 0.01, False),  # below min_gain alone: not handed over
    ]
    first, _ = _ranked(Diagnosis(findings, ["theta"], [], [], [], {}, {}, []), lib, DiagnoseParams())
    assert [(f.label, c.harmonic) for f, c in first] == [
        ("dtheta/dt: SineCoupling(theta)", 1),
        ("dtheta/dt: SineCoupling(theta, k=2)", 2),
    ]
