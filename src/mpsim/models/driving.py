"""Inputs of a driven white-box model (`model=equations` with `inputs:` in its spec): the data's controls matched
to the spec's inputs by name, and held between samples as the data say.

The equations see the inputs in physical units, as recorded: a white-box model's parameters multiply them
(`(k*u - Fv*v)/M`), so z-scoring them (as learned models do, `mpsim.models.controls`) would change what the
parameters mean.

Between two samples t_k, t_{k+1} the input is held as the data's metadata say, ``meta["input_hold"]``:

- ``linear`` (the default): interpolated linearly between u_k and u_{k+1}, a continuous signal, so one adaptive
  solve runs over the whole grid;
- ``zoh`` (zero-order hold, as a DAC drives a motor): u_k on [t_k, t_{k+1}). The input jumps at every sample,
  so no step of the solver may straddle one: mpsim's dopri5 steps to every sample time and restarts there
  (`ODESolver(..., restart=True)`); other solvers run one interval at a time with the interval's sample fixed
  (`integrate_held`). Measured on 2000 samples (16 trajectories, a 2-state pendulum, one input, 1 CPU thread):
  1.0 s per rollout with `linear` against 2.2 s with `zoh` at rtol = atol = 1e-4 (2.2 against 7 field
  evaluations per sample); 23 s against 2.2 s at 1e-7, where the kinks of the interpolated input make `linear`
  the costly one. Solving interval by interval instead of restarting costs another 10–15 %. With a delayed
  effect (fixed-step RK4 with history) the input is read by time: a stage on a sample time sees the new sample.

A one-step batch (every sample's interval from its observed state, `EquationsModel.one_step`) holds each row's
input on its own interval (`IntervalInput`); the intervals are independent, so both holds run as one batched
solve.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from mpsim.errors import ConfigError
from mpsim.signals import HOLDS as HOLDS
from mpsim.signals import GridInput as GridInput
from mpsim.signals import input_hold as input_hold


def check_input_names(declared: Sequence[str], given: Sequence[str], where: str = "model.spec") -> None:
    """Refuse data whose control names are not the spec's inputs, in the same order (one message naming both).

    Args:
        declared: the spec's `inputs`.
        given: the data's control names (`meta["control_names"]`).
    """
    declared, given = list(declared), list(given)
    if declared == given:
        return
    fix = (
        "Map the file's columns to the inputs by name with data.control_columns=[...] (in the spec's order) "
        "or data.columns={<input>: <column>}"
    )
    if not declared:
        raise ConfigError(
            f"{where} declares no inputs but the data have the controls {given}; declare them under inputs: in "
            f"the spec (e.g. inputs: {given}) if the equations use them, or read the file without them (drop them "
            "from data.control_columns)."
        )
    if not given:
        raise ConfigError(f"{where}.inputs {declared} are not in the data: the data have no controls. {fix}.")
    if sorted(declared) == sorted(given):
        why = "the same names in another order"
    else:
        missing = [n for n in declared if n not in given]
        extra = [n for n in given if n not in declared]
        why = f"missing {missing}, extra {extra}" + (": a control the equations do not use is refused" * bool(extra))
    raise ConfigError(f"{where}.inputs {declared} do not match the data's controls {given} ({why}). {fix}.")


def check_input_count(declared: Sequence[str], control_dim: int, where: str = "model.spec") -> None:
    """Refuse data with another number of controls per node than the spec has inputs (names unknown here)."""
    if control_dim == len(declared):
        return
    if not declared:
        raise ConfigError(
            f"{where} declares no inputs but the data have {control_dim} control(s) per node; declare them under "
            "inputs: in the spec if the equations use them, or read the file without them (drop them from "
            "data.control_columns)."
        )
    raise ConfigError(
        f"{where}.inputs {list(declared)} are {len(declared)} per node but the data have {control_dim} control(s). "
        "Map the file's columns to the inputs by name with data.control_columns=[...] (in the spec's order) or "
        "data.columns={<input>: <column>}."
    )


class IntervalInput:
    """The inputs of a one-step batch: row m integrates one sample interval [0, dt] (local time) from its sample
    u0[m], held (zoh) or moving linearly to the next sample u0[m] + du[m] (linear)."""

    def __init__(
        self,
        u0: torch.Tensor,  # [M, N, C] each row's sample at the interval's start
        du: torch.Tensor | None,  # [M, N, C] the change to the next sample (None: zero-order hold)
        dt: torch.Tensor,  # [] the interval's length
    ) -> None:
        self.u0, self.du, self.dt = u0, du, dt

    def __call__(self, t: torch.Tensor) -> torch.Tensor:  # t: [] local time in [0, dt]
        """[M, N, C] every row's input at local time `t`."""
        if self.du is None:
            return self.u0
        w = (t / self.dt).clamp(0.0, 1.0).to(self.u0)
        return self.u0 + w * self.du
