"""A driven mass measured by its position only (issue 60, item 4): the data and the nominal model.

Truth: q' = v, v' = (u − c·v − Fc·tanh(v/ε))/m, with a multisine force u held between samples (a DAC's
zero-order hold), integrated here by RK4 at 1/20 of the sample step (numpy; not mpsim's simulator). One long
recording per seed is cut into 1 s segments; only q is recorded, with sensor noise and quantised as an encoder
would; v is estimated from q (`mpsim.data.latent.estimate_latent`: a Savitzky–Golay derivative).
"""

from __future__ import annotations

import numpy as np
import torch

from mpsim.data.latent import estimate_latent
from mpsim.data.trajectories import Trajectories
from mpsim.models.equations import EquationsModel
from mpsim.solvers.odeint import ODESolver

MASS, VISCOUS, COULOMB, EPS = 1.0, 0.4, 0.3, 1e-3
DT, SEGMENT_S, SUBSTEPS = 0.01, 1.0, 20
QUANTUM, NOISE = 1e-6, 2e-6
NOMINAL = {
    "states": ["q", "v"],
    "inputs": ["u"],
    "equations": {"q": "v", "v": "(u - c*v)/m"},
    "params": {"c": VISCOUS, "m": MASS},
    "nodes": 1,
}


def multisine(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:  # t: [T] -> [T]
    """A force of five sines (0.3–3 Hz, random phases), about 1 N RMS: the mass reverses often."""
    freqs = np.array([0.3, 0.7, 1.3, 2.1, 3.0])
    phases = rng.uniform(0, 2 * np.pi, len(freqs))
    return 0.65 * np.sin(2 * np.pi * freqs[:, None] * t[None] + phases[:, None]).sum(0)


def simulate(n_segments: int, coulomb: float, seed: int) -> tuple[np.ndarray, ...]:
    """(t [T], q [S, T] measured, v [S, T] true, u [S, T]) of `n_segments` consecutive 1 s segments of one
    recording (RK4, u held)."""
    rng = np.random.default_rng(seed)
    per = round(SEGMENT_S / DT)
    n = n_segments * per + 1
    t = np.arange(n) * DT
    u = multisine(t, rng)
    h = DT / SUBSTEPS

    def f(x: np.ndarray, force: float) -> np.ndarray:  # x: [2]
        return np.array([x[1], (force - VISCOUS * x[1] - coulomb * np.tanh(x[1] / EPS)) / MASS])

    x, q, v = np.zeros(2), np.empty(n), np.empty(n)
    for k in range(n):  # the reference integrator: a loop in time (numpy, one trajectory)
        q[k], v[k] = x
        for _ in range(SUBSTEPS):
            k1 = f(x, u[k])
            k2 = f(x + h / 2 * k1, u[k])
            k3 = f(x + h / 2 * k2, u[k])
            k4 = f(x + h * k3, u[k])
            x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    q = QUANTUM * np.round((q + NOISE * rng.standard_normal(n)) / QUANTUM)
    idx = np.arange(n_segments)[:, None] * per + np.arange(per + 1)[None]  # [S, T] overlapping by one sample
    return t[: per + 1], q[idx], v[idx], u[idx]


def measured(n_segments: int, coulomb: float, seed: int) -> Trajectories:
    """The segments as mpsim reads them with data.observed=[q]: q measured, v estimated from it."""
    t, q, _, u = simulate(n_segments, coulomb, seed)
    data = Trajectories(
        t=torch.as_tensor(t),
        x=torch.as_tensor(q)[:, :, None, None],
        edge_index=torch.zeros(2, 0, dtype=torch.long),
        u=torch.as_tensor(u)[:, :, None, None],
        meta={"state_names": ["q"], "control_names": ["u"], "input_hold": "zoh", "source": "mass.csv"},
    )
    return estimate_latent(data, {"v": "q"}, states=["q", "v"])


def nominal_model(train: Trajectories) -> EquationsModel:
    """The nominal model (no Coulomb friction), float64, normalised on `train` (v's statistics from its estimate)."""
    model = EquationsModel(2, 1, spec=NOMINAL, solver=ODESolver("dopri5", rtol=1e-7, atol=1e-9)).double()
    model.bind_effects(train.state_names)
    model.bind_inputs(train.control_names)
    flat = train.x.reshape(-1, 2).double()
    model.set_normalisation(flat.mean(0), flat.std(0))
    return model
