"""One source for the residual loop's settings and effect kinds: `conf/diagnose.yaml` states exactly the
defaults of `DiagnoseParams`, and an unknown kind is refused."""

import dataclasses
from pathlib import Path

import pytest
import yaml

from mpsim.diagnose.params import DEFAULT_KINDS, KIND_COMPLEXITY, DiagnoseParams
from mpsim.errors import ConfigError

CONF = Path(__file__).resolve().parents[2] / "src" / "mpsim" / "conf" / "diagnose.yaml"


def test_diagnose_yaml_states_the_schema_defaults():
    stated = yaml.safe_load(CONF.read_text())["diagnose"]
    defaults = dataclasses.asdict(DiagnoseParams())
    assert stated == defaults


def test_effect_kinds_are_one_list():
    assert DEFAULT_KINDS == list(KIND_COMPLEXITY)
    import mpsim.effects as fx

    assert all(isinstance(getattr(fx, k, None), type) for k in DEFAULT_KINDS)  # each is an effect class


def test_an_unknown_kind_is_refused_with_a_suggestion():
    with pytest.raises(ConfigError, match="'LinearDamping'"):
        DiagnoseParams(kinds=["LinearDampin"])


@pytest.mark.parametrize(
    "change, match",
    [
        ({"n_boot": 0}, "diagnose.n_boot must be >= 1"),  # was a ZeroDivisionError deep in the selection
        ({"rounds": 0}, "diagnose.rounds must be >= 1"),
        ({"fit_window": 1}, "diagnose.fit_window must be >= 2"),
        ({"horizon": 0}, "diagnose.horizon >= 1"),
        ({"margin": float("nan")}, "diagnose.margin must be a finite number >= 0"),
        ({"tolerance": 0.0}, "diagnose.tolerance must be a finite number > 0"),
        ({"delays": [0.5, -1.0]}, "diagnose.delays must be times > 0"),
    ],
)
def test_settings_out_of_range_are_refused(change, match):
    with pytest.raises(ConfigError, match=match):
        DiagnoseParams(**change)
    DiagnoseParams(min_explained=1.5, horizon=3, delays=[0.5])  # in range, even where unreachable, is accepted


def test_windows_too_short_for_a_phased_drive_say_so():
    # a model that tracks the data for 2 steps gives 2-step windows: no step is left after the phase's warm-up
    import torch

    from mpsim.data.trajectories import Trajectories
    from mpsim.diagnose.perrecord import phased_heldout
    from mpsim.errors import DataError

    data = Trajectories(t=torch.arange(3) * 0.1, x=torch.zeros(2, 3, 2, 1), edge_index=torch.zeros(2, 0).long())
    trial = type("Trial", (), {"effects": [object()]})()
    with pytest.raises(DataError, match="windows are 2 steps.*diagnose.horizon=3 or more"):
        phased_heldout(None, trial, data, 2, 1)


def test_a_phased_drive_that_cannot_be_tested_is_rejected_with_its_reason_and_the_diagnosis_goes_on():
    # 2-step held-out windows leave no step after the phase warm-up: the candidate is not tested (it was a
    # DataError that ended the whole diagnosis), the others are judged, and the summary names it as untested
    from types import SimpleNamespace

    import torch

    from mpsim.diagnose.heldout import _best_text
    from mpsim.diagnose.perrecord import phase_warmup
    from mpsim.diagnose.trial import Trial, TrialSetting, try_candidate

    assert phase_warmup(2, 3) is None and phase_warmup(3, 13) == 3 and phase_warmup(50, 201) == 50
    finding = SimpleNamespace(label="dv/dt: PeriodicForcing(ω=3.1, a phase per recording)", kind="PeriodicForcing",
                              accepted=True, coef=[1.0])  # fmt: skip
    e = torch.tensor([2e-3, 1e-3])
    short, long = SimpleNamespace(n_times=3), SimpleNamespace(n_times=41)
    phased = SimpleNamespace(params={"phased": True})
    for test, null_test in ((short, long), (long, short)):  # the null records may be the shorter ones
        setting = TrialSetting(None, e, e / 100, None, test, None, null_test, 2, None, ["x", "v"])
        trial, model, e_after = try_candidate(setting, None, e, phased, finding)
        assert not trial.accepted and trial.reason.startswith("not tested: the held-out windows are 2 steps")
        assert "diagnose.horizon=3 or more" in trial.reason and model is None and e_after is e
    other = Trial(
        "dv/dt: LinearDamping(v)", "LinearDamping", True, {}, {}, {}, 1.5e-3, 1e-3, 5e-4, 1e-4, 0.0, False, "x"
    )
    text = _best_text([trial, other], 1.5e-3, 1e-5)
    assert text.startswith("best candidate dv/dt: LinearDamping(v): held-out MSE 0.0015 → 0.001")
    assert "; dv/dt: PeriodicForcing(ω=3.1, a phase per recording) not tested: the held-out windows" in text
    assert _best_text([trial], 1.5e-3, 1e-5).startswith(
        "dv/dt: PeriodicForcing(ω=3.1, a phase per recording) not tested"
    )
