"""The nominal white-box model the residual-loop tests diagnose: a spec as the scientist writes it, float64, tight
dopri5, bound to the data's state names and normalised on the held-in records."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from mpsim.data.trajectories import Trajectories
from mpsim.effects import Effect
from mpsim.models.equations import EquationsModel
from mpsim.solvers.odeint import ODESolver


def nominal_model(spec: dict[str, Any], train: Trajectories, effects: Sequence[Effect] = ()) -> EquationsModel:
    d = train.state_dim
    solver = ODESolver("dopri5", rtol=1e-7, atol=1e-9)
    model = EquationsModel(d, 0, spec=spec, effects=list(effects), solver=solver).double()
    model.bind_effects(train.state_names)
    flat = train.x.reshape(-1, d)
    model.set_normalisation(flat.mean(0), flat.std(0))
    return model
