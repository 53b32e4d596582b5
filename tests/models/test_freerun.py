"""Free-run evaluation of whole records (`mpsim.models.freerun`): the chunked (parareal) run equals the run of each
record in one piece, a latent start is fitted to the first samples, and the scores are the field's."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mpsim.data.segments import whole_records
from mpsim.data.trajectories import Trajectories
from mpsim.models.equations import EquationsModel
from mpsim.models.freerun import default_init_samples, free_run, score_record
from mpsim.solvers import ODESolver

SPEC = {
    "states": ["q", "v"],
    "inputs": ["u"],
    "equations": {"q": "v", "v": "u - c*v - k*q"},
    "params": {"c": 0.4, "k": 4.0},
}


def _truth(n: int, dt: float, amp: float, q0: float) -> Trajectories:
    """A damped driven oscillator from an integrator of the test's own (RK4 at dt/20), input linear between
    samples; positions and velocities."""
    t = dt * np.arange(n)
    u = amp * (np.sin(1.3 * t) + 0.5 * np.sin(3.1 * t + 1.0))
    y, h, xs = np.array([q0, 0.0]), dt / 20, []

    def f(y: np.ndarray, uk: float) -> np.ndarray:
        return np.array([y[1], uk - 0.4 * y[1] - 4.0 * y[0]])

    for k in range(n):  # a loop over the samples of the test's reference integrator
        xs.append(y.copy())
        if k + 1 == n:
            break
        for j in range(20):
            a, b = u[k] + (u[k + 1] - u[k]) * j / 20, u[k] + (u[k + 1] - u[k]) * (j + 0.5) / 20
            c = u[k] + (u[k + 1] - u[k]) * (j + 1) / 20
            k1 = f(y, a)
            k2 = f(y + h / 2 * k1, b)
            k3 = f(y + h / 2 * k2, b)
            k4 = f(y + h * k3, c)
            y = y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    meta = {"state_names": ["q", "v"], "control_names": ["u"], "input_hold": "linear", "source": f"r{amp}.csv"}
    x = torch.tensor(np.array(xs)).reshape(1, n, 1, 2)
    return Trajectories(t=torch.tensor(t), x=x, edge_index=torch.zeros(2, 0, dtype=torch.long),
                        u=torch.tensor(u).reshape(1, n, 1, 1), meta={**meta, "t0": [0.0]})  # fmt: skip


def _model() -> EquationsModel:
    model = EquationsModel(2, control_dim=1, spec=SPEC, solver=ODESolver("dopri5")).double()
    model.bind_inputs(["u"])
    model.set_normalisation(torch.zeros(2, dtype=torch.float64), torch.ones(2, dtype=torch.float64))
    return model


def _positions_only(records: Trajectories) -> Trajectories:
    """The records as measured: q; v a poor first estimate (80 % of it, plus 0.1), as a latent state."""
    x = torch.cat([records.x[..., :1], 0.8 * records.x[..., 1:] + 0.1], dim=-1)
    return Trajectories(t=records.t, x=x, edge_index=records.edge_index, u=records.u,
                        meta={**records.meta, "observed": ["q"], "estimated": {"v": "a poor guess"}})  # fmt: skip


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_the_chunked_run_is_the_whole_run_and_the_latent_start_is_found():
    records = _positions_only(whole_records([_truth(1201, 0.05, 1.0, 0.3), _truth(1001, 0.05, 2.0, -0.5)]))
    chunked = free_run(_model(), records, chunk=200)
    whole = free_run(_model(), records, chunk=10**6)
    assert chunked.passes >= 2 and whole.passes == 0
    assert float((chunked.pred - whole.pred).abs().max()) < 1e-6
    assert chunked.init_samples == default_init_samples(records) == 3
    truth = whole_records([_truth(1201, 0.05, 1.0, 0.3), _truth(1001, 0.05, 2.0, -0.5)])
    for r, length in enumerate((1201, 1001)):  # the exact model, started from 3 samples: the record, throughout
        err = (chunked.pred[r, :length] - truth.x[r, :length]).abs().max()
        assert float(err) < 1e-4, (r, float(err))
        assert chunked.scores[r]["q"]["fit"] > 99.9 and chunked.scores[r]["q"]["samples"] == length - 3
    assert "v" not in chunked.scores[0]  # a latent state is no measured channel


def test_scores_are_rmse_nrmse_and_fit_after_the_start():
    t = torch.arange(6.0)
    true = torch.tensor([9.0, 9.0, 1.0, 2.0, 3.0, 4.0]).reshape(6, 1, 1)
    pred = true.clone()
    pred[2:, 0, 0] += torch.tensor([1.0, -1.0, 1.0, -1.0])
    records = Trajectories(
        t=t, x=true[None], edge_index=torch.zeros(2, 0, dtype=torch.long), meta={"state_names": ["y"]}
    )
    s = score_record(pred, true, records, start=2, length=6)["y"]
    spread = math.sqrt(np.var([1.0, 2.0, 3.0, 4.0]))
    assert s["rmse"] == pytest.approx(1.0) and s["nrmse"] == pytest.approx(1 / spread)
    assert s["fit"] == pytest.approx(100 * (1 - 1 / spread)) and s["samples"] == 4
