"""What the one-step screen (`mpsim.diagnose.search.find_effects`) finds: one `Finding` per selected candidate
and state variable, and the `Diagnosis` that holds them with the numbers they were judged by."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch

from mpsim.diagnose.residual import Residual


@dataclass
class Finding:
    """One candidate for one state variable, with the evidence for and against it: one the screen's joint BIC fit
    selected, or (`selected` False) the best candidate of a kind the fit did not select on that row — the one of
    its kind that explains most of the row alone, with its coefficients fitted alone; never accepted by the screen,
    it is there for the held-out judgement (`heldout._ranked`), which decides between kinds."""

    target: int
    label: str
    kind: str
    coef: list[float]
    interval: list[tuple[float, float]]
    gain: float  # share of the residual sum of squares it removed on entry (not selected: its share alone)
    explained_rms: float  # the part of the residual it accounts for, in the residual's units (RMS)
    alone: float  # share it explains on its own
    inclusion: float  # bootstrap inclusion frequency
    threshold: float  # the explained RMS it had to reach (null_factor × what any candidate explains on null data)
    accepted: bool
    reason: str
    effect: dict[str, Any]  # Hydra config of the effect with the fitted coefficients
    selected: bool = True  # chosen by the joint BIC fit (False: the best of its kind on the row, fitted alone)

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass
class Diagnosis:
    """Everything `find_effects` measured (plain data for diagnosis.json, tensors for the plots)."""

    findings: list[Finding]
    state_names: list[str]
    residual_rms: list[float]  # per state variable, on the data
    null_rms: list[float]  # per state variable, on the null data
    null_level: list[float]  # per state variable: largest RMS any candidate explains on the null data
    explained: dict[str, list[float]]  # candidate label -> share explained alone, per state variable
    omegas: dict[int, float]  # forcing frequency found per state variable
    noise_std: list[float]  # estimated measurement noise per state variable
    residual: Residual | None = None
    periodograms: dict[int, tuple[torch.Tensor, torch.Tensor]] = field(default_factory=dict)
    parameter_shifts: dict[str, float] = field(default_factory=dict)  # refit of the model's own parameters
    represented: list[str] = field(default_factory=list)  # effect kinds the model can express itself
    not_considered: list[str] = field(default_factory=list)  # kinds that cannot be told apart from model error
    searched: list[str] = field(default_factory=list)  # state rows searched (the dynamic rows by default)
    phased_omegas: dict[int, float] = field(default_factory=dict)  # drive frequencies with a phase per recording
    horizon: int | None = None  # steps the model tracks the screened data (the held-out windows' length)
    equivalent_forms: list[str] = field(default_factory=list)  # candidates left out: a simpler kind equals them here
    #: per-node variants the screen added (their shared candidate's label, the nodes) and why, in words
    per_node: list[tuple[str, tuple[int, ...]]] = field(default_factory=list)
    per_node_notes: list[str] = field(default_factory=list)

    @property
    def accepted(self) -> list[Finding]:
        return [f for f in self.findings if f.accepted]

    def as_dict(self) -> dict[str, Any]:
        return {
            "effects_found": [f.as_dict() for f in self.accepted],
            "candidates_considered": [f.as_dict() for f in self.findings],
            "state_names": self.state_names,
            "residual_rms": self.residual_rms,
            "null_rms": self.null_rms,
            "null_level": self.null_level,
            "explained_alone": self.explained,
            "forcing_omegas": {self.state_names[k]: v for k, v in self.omegas.items()},
            "noise_std_estimate": self.noise_std,
            "parameter_shifts": self.parameter_shifts,
            "represented_by_model": self.represented,
            "not_considered": self.not_considered,
            "searched_rows": self.searched,
            "equivalent_forms": self.equivalent_forms,
            "per_node": self.per_node_notes,
        }
