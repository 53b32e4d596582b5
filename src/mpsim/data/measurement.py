"""A clean trajectory as the instrument would have recorded it: the null data of the residual loop carry the
data's own noise and quantisation, and their unmeasured states are estimated the way the data's were.

Per measured state, the noise added is what the data's noise level leaves beyond quantisation,
σ_extra = √max(σ² − δ²/12, 0) (a uniform rounding error of one step δ has spread δ/√12), and the value is then
rounded to the step. δ comes from the recording as read, before any resampling (``meta["noise"]``, written by
`mpsim.data.measured`), else from the values themselves (`mpsim.data.noise.grid_quantum`). Unmeasured states
(``meta["observed"]``) are then estimated from the noisy, rounded measured states by the rule the data's were
(`mpsim.data.latent.estimate_latent` with ``meta["derived_from"]``), so a clean twin of the data and the data
are judged alike.
"""

from __future__ import annotations

import math

import torch

from mpsim.data.latent import estimate_latent
from mpsim.data.noise import grid_quantum
from mpsim.data.trajectories import Trajectories


def quanta(data: Trajectories) -> list[float | None]:
    """Per state: the quantisation step of the recording as read (``meta["noise"]``), else of the values held."""
    recorded = data.meta.get("noise") or {}
    out: list[float | None] = []
    for k, name in enumerate(data.state_names):  # a loop over the few state variables
        entry = recorded.get(name) if isinstance(recorded, dict) else None
        if isinstance(entry, dict) and "quantum" in entry:
            q = entry["quantum"]
            out.append(float(q) if isinstance(q, int | float) and q > 0 else None)
        else:
            out.append(grid_quantum(data.x[..., k]))
    return out


def as_measured(
    clean: torch.Tensor,  # [B, T, N, D] a clean trajectory on the data's grid `t`
    t: torch.Tensor,  # [T] its times
    data: Trajectories,
    sigma: torch.Tensor,  # [D] the data's measurement-noise level per state
    gen: torch.Generator,
) -> torch.Tensor:
    """[B, T, N, D] `clean` with the data's noise and quantisation on its measured states, and its unmeasured
    states estimated from them as the data's were (module docstring)."""
    x = clean.double().cpu().clone()
    observed, latent = data.observed_index, data.latent_index
    steps = quanta(data)
    noise = torch.randn(x.shape, generator=gen, dtype=torch.float64)
    for k in observed:  # a loop over the few measured variables
        s, q = float(sigma[k]), steps[k]
        extra = math.sqrt(max(s * s - (q * q / 12.0 if q else 0.0), 0.0))
        x[..., k] = x[..., k] + noise[..., k] * extra
        if q:
            x[..., k] = torch.round(x[..., k] / q) * q
    x = x.nan_to_num()
    rates = data.meta.get("derived_from") or {}
    names = data.state_names
    if not latent or not rates:
        return x
    measured = Trajectories(
        t=t,
        x=x[..., observed],
        edge_index=data.edge_index,
        meta={**data.meta, "state_names": [names[k] for k in observed]},
    )
    measured.meta.pop("observed", None)
    filled = estimate_latent(measured, {names[k]: rates[names[k]] for k in latent}, states=names)
    return filled.x.double()
