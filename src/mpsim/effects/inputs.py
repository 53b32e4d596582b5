"""Effects on the input path: what reaches the system is not quite the input that was recorded.

`InputGain`: the input u_c reaches the system as g_b·u_c, with a gain g_b of its own in every recording b (an
amplifier's or a motor constant's scale that differs between sessions; the DFKI pendulum's torque).
`DeadZone`: sign(u)·max(|u| − w, 0), an amplifier or valve that passes nothing below w.
`InputSaturation`: clip(u, −U, U), an actuator that cannot deliver more than U.
None is a term of dx/dt: the model passes its own input through them (`through`) before its equations read it, so
only a model that reads its inputs applies them (`model=equations`: `EquationsModel`). The thresholds are fitted
as they are (continuous, piecewise linear in the threshold: over many samples the loss is smooth enough for
L-BFGS), as their logarithm (they stay positive); the reported value is the threshold itself.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import nn

from mpsim.effects.base import Effect
from mpsim.errors import ConfigError


class InputGain(Effect):
    """u_c → g_b·u_c: the input `input` reaches the system with a gain g_b of its own in every recording b.

    The gains belong to the recordings, not to the model (a new recording brings its own): rollouts must batch
    the recordings in the order of `gains` (the residual loop fits the gains of held-in records, and estimates
    those of held-out records from a warm-up window). With one recording, or gains that agree, it is the input's
    coefficient in the equations, not a finding. The coefficients are g_b − 1 (zero: the nominal input).

    Args:
        input: the input's name (or index) among the spec's `inputs:`.
        gains: g_b, one per recording (default: one recording, gain 1).
        target: the state row the residual loop found it on (the gain acts wherever the equations read u).
    """

    basis = ("u",)
    #: reads the record's place in the batch: a batch that reorders or tiles records says which row is which
    #: (`Inputs.meta["record_index"]`); it reads no time, so windows still batch
    per_record = True
    #: applied by the model to its own inputs, not added to dx/dt (`EquationsModel`)
    acts_on_inputs = True

    def __init__(
        self,
        input: str | int = 0,
        gains: Sequence[float] | None = None,
        target: str | int = 0,
        source: str | int | None = None,
        learnable: bool = True,
    ) -> None:
        super().__init__(0.0, target, source, learnable)
        values = [float(g) - 1.0 for g in (gains if gains is not None else [1.0])]
        if not values:
            raise ConfigError("InputGain.gains must list one gain per recording; got an empty list.")
        self.coef = nn.Parameter(torch.tensor(values, dtype=torch.float64), requires_grad=learnable)
        self.input_ref = input

    @property
    def gains(self) -> list[float]:
        return [1.0 + float(c) for c in self.coef.detach()]

    def channel(self, input_names: Sequence[str]) -> int:
        """The index of `input` among the model's inputs (ConfigError naming them when it is not one)."""
        ref = self.input_ref
        if isinstance(ref, int) and 0 <= ref < len(input_names):
            return ref
        if isinstance(ref, str) and ref in input_names:
            return list(input_names).index(ref)
        raise ConfigError(f"InputGain.input={ref!r} is not an input of the model; its inputs: {list(input_names)}.")

    def through(
        self,
        u: torch.Tensor,  # [M, N, C] inputs, one row per batch row
        channel: int,
        records: torch.Tensor | None = None,  # [M] the recording of each row (None: row b is recording b)
    ) -> torch.Tensor:
        """[M, N, C] u with channel `channel` of each row times its recording's gain g_b. A batch whose rows are not
        the recordings in order (windows batched window-major, one-step batches, outputs at every time) names each
        row's recording in `records`; without it the rows must be the recordings, one each."""
        b = self.coef.numel()
        if records is None:
            if u.shape[0] != b:
                raise ValueError(
                    f"InputGain has {b} gains (one per recording) but the batch has {u.shape[0]} rows and does not "
                    "say which recording each row is."
                )
            rel = self.coef.to(u)
        else:
            if records.numel() != u.shape[0] or (records.numel() and int(records.max()) >= b):
                raise ValueError(
                    f"InputGain has {b} gains; the batch's record index does not fit its {u.shape[0]} rows."
                )
            rel = self.coef.to(u)[records.to(u.device)]  # [M] g − 1 of each row's recording
        mask = torch.zeros(u.shape[-1], dtype=u.dtype, device=u.device)
        mask[channel] = 1.0  # [C] only the named input is scaled
        return u * (1.0 + rel[:, None, None] * mask)

    def features(self, t, x, ctx):
        return _only_equations(self)

    def forward(self, t, x, ctx):
        return _only_equations(self)

    def describe(self) -> str:
        gains = ", ".join(f"{g:.4g}" for g in self.gains)
        return f"{self.input_ref} → g·{self.input_ref}, a gain per recording: {gains}"

    def config(self) -> dict[str, Any]:
        cfg = super().config()
        del cfg["source"], cfg["coef"]
        return {**cfg, "input": self.input_ref, "gains": self.gains}

    def extra_repr(self) -> str:
        return f"input={self.input_ref}, gains={[round(g, 6) for g in self.gains]}"


def _only_equations(effect: Effect) -> torch.Tensor:
    raise ConfigError(
        f"{type(effect).__name__}({getattr(effect, 'input_ref', '')}) acts on a model's own input: only "
        "model=equations applies it (it is no term a system or another model can add to dx/dt)."
    )


class _Threshold(Effect):
    """An input-path effect with one positive threshold (fitted as its log) on input `input`."""

    basis = ("u",)
    acts_on_inputs = True
    #: the threshold's name in configs and reports
    key = "threshold"

    def __init__(
        self,
        input: str | int = 0,
        threshold: float = 1.0,
        target: str | int = 0,
        source: str | int | None = None,
        learnable: bool = True,
    ) -> None:
        super().__init__(0.0, target, source, learnable)
        if not threshold > 0:
            raise ConfigError(f"{type(self).__name__}.{self.key} must be > 0; got {threshold}.")
        # the log threshold is the one fitted coefficient (coef holds it: the loop's fits free `coef`)
        self.coef = nn.Parameter(torch.tensor([math.log(threshold)], dtype=torch.float64), requires_grad=learnable)
        self.input_ref = input

    @property
    def threshold(self) -> float:
        return float(self.coef.detach()[0].exp())

    channel = InputGain.channel

    def shape(self, v: torch.Tensor, w: torch.Tensor) -> torch.Tensor:  # v: [M, N] one input; w: [] threshold
        """[M, N] what reaches the system of the input v."""
        raise NotImplementedError

    def through(
        self,
        u: torch.Tensor,  # [M, N, C] inputs
        channel: int,
        records: torch.Tensor | None = None,  # [M] each row's recording (unused: the same threshold for all)
    ) -> torch.Tensor:
        """[M, N, C] u with channel `channel` shaped (`shape`), the others as they are."""
        w = self.coef[0].to(u).exp()
        shaped = self.shape(u[..., channel], w)
        return torch.cat([u[..., :channel], shaped[..., None], u[..., channel + 1 :]], dim=-1)

    def features(self, t, x, ctx):
        return _only_equations(self)

    def forward(self, t, x, ctx):
        return _only_equations(self)

    def config(self) -> dict[str, Any]:
        cfg = super().config()
        del cfg["source"], cfg["coef"]
        return {**cfg, "input": self.input_ref, self.key: self.threshold}

    def extra_repr(self) -> str:
        return f"input={self.input_ref}, {self.key}={self.threshold:.6g}"


class DeadZone(_Threshold):
    """u → sign(u)·max(|u| − w, 0): the input `input` passes nothing below the width w and w less above it.

    Args:
        input: the input's name (or index) among the spec's `inputs:`.
        width: w > 0.
        target: the state row the residual loop found it on (it acts wherever the equations read u).
    """

    key = "width"

    def __init__(
        self,
        input: str | int = 0,
        width: float = 1.0,
        target: str | int = 0,
        source: str | int | None = None,
        learnable: bool = True,
    ) -> None:
        super().__init__(input, width, target, source, learnable)

    def shape(self, v, w):
        return v - torch.maximum(torch.minimum(v, w), -w)  # v − clip(v, −w, w)

    def describe(self) -> str:
        return (
            f"{self.input_ref} → sign({self.input_ref})·max(|{self.input_ref}| − {self.threshold:.4g}, 0) (a dead zone)"
        )


class InputSaturation(_Threshold):
    """u → clip(u, −U, U): the input `input` cannot reach the system beyond the limit U.

    Args:
        input: the input's name (or index) among the spec's `inputs:`.
        limit: U > 0.
        target: the state row the residual loop found it on (it acts wherever the equations read u).
    """

    key = "limit"

    def __init__(
        self,
        input: str | int = 0,
        limit: float = 1.0,
        target: str | int = 0,
        source: str | int | None = None,
        learnable: bool = True,
    ) -> None:
        super().__init__(input, limit, target, source, learnable)

    def shape(self, v, w):
        return torch.maximum(torch.minimum(v, w), -w)

    def describe(self) -> str:
        return f"{self.input_ref} → clip({self.input_ref}, ±{self.threshold:.4g}) (a saturation)"


def through_all(
    effects: Sequence[Effect],
    input_names: Sequence[str],
    u: torch.Tensor,  # [M, N, C] inputs
    records: torch.Tensor | None = None,  # [M] each row's recording (None: row b is recording b)
) -> torch.Tensor:
    """[M, N, C] the inputs as a model's equations read them: through each of its input-path effects, in order."""
    for e in effects:  # one or two named effects
        u = e.through(u, e.channel(input_names), records)  # type: ignore[operator]
    return u


def record_index(meta: dict[str, Any], b: int) -> torch.Tensor:
    """[B] the recording of each of a batch's B rows (`meta["record_index"]`, else row b is recording b)."""
    given = meta.get("record_index")
    return torch.arange(b) if given is None else torch.as_tensor(given)
