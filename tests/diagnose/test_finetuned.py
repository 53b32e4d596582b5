"""Acceptance by finetuning (the black-box path of fix=true): candidate + finetune against the same finetune
without it. The finetune here is a multiple-shooting fit of every trainable parameter (a stand-in for the
trainer that keeps the test fast); the data come from the pendulum generator, not Lorenz (case 2)."""

import copy
import math

import pytest
import torch

from mpsim.diagnose.findings import Diagnosis, Finding
from mpsim.diagnose.finetuned import PHASES_AGREE, finetune_candidates, judge_by_finetune, serial, shared_phase
from mpsim.diagnose.heldout import EFFECTS_NAMED, UNEXPLAINED
from mpsim.diagnose.library import Candidate
from mpsim.diagnose.loop import screen
from mpsim.diagnose.params import DiagnoseParams
from mpsim.diagnose.shooting import shooting_fit, window_error
from mpsim.effects import LinearDamping
from mpsim.systems import CoupledPendulums
from tests.helpers import declared_pendulums


def _finetune(train, tags):
    def finetune(model, tag):  # every trainable parameter refit: what a finetune of a white-box model reaches
        tags.append(tag)
        free = [p for p in model.parameters() if p.requires_grad]
        shooting_fit(model, train.subset(slice(0, 6)), 20, free, 15)
        return model, f"{tag}/best.ckpt"

    return finetune


def _setup(effects, seed):
    data = CoupledPendulums(effects=effects).generate(24, seed=seed, horizon=80)
    train, test = data.subset(slice(0, 16)), data.subset(slice(16, 24))
    return train, test, declared_pendulums(train)


PARAMS = DiagnoseParams(n_boot=20)


@pytest.fixture(scope="module")
def damped():
    """(held-in, held-out, the declared undamped model, its screen) on data with hidden damping 0.2."""
    train, test, model = _setup([LinearDamping(0.2, target="omega")], seed=0)
    return train, test, model, screen(model, train, PARAMS, 0)


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_names_what_the_control_finetune_cannot_learn(damped):
    train, test, model, (diag, library) = damped
    tags: list[str] = []
    fj = judge_by_finetune(
        model, diag, library, train, test, 20, 1e-10, PARAMS, serial(_finetune(train, tags)), "round1"
    )
    assert tags[0] == "round1/control" and len(tags) == 1 + len(fj.trials)  # the control first, then each candidate
    assert fj.verdict == EFFECTS_NAMED
    (named,) = fj.named
    assert named.label == "domega/dt: LinearDamping(omega)"
    assert named.values["coef"] == pytest.approx(0.2, rel=0.05)
    lo, hi = named.interval["coef"]
    assert lo < named.values["coef"] < hi  # the interval is that of the value reported
    assert fj.error_final < 0.1 * fj.error_control  # the control (g, k refit) cannot learn damping
    assert fj.checkpoint == tags[1 + fj.trials.index(named)] + "/best.ckpt" != "round1/control/best.ckpt"
    assert float(window_error(fj.model, test, 20).mean()) == pytest.approx(fj.error_final)


@pytest.mark.slow  # a whole residual-loop run: `pytest -m slow` (.ci/run runs it)
def test_a_candidate_that_the_control_matches_is_not_named(damped):
    # the screen of damped data proposes damping; on clean data the finetune drives it to ~0 and the model with
    # it predicts no better than the control
    *_, (diag, library) = damped
    train, test, model = _setup([], seed=1)
    fj = judge_by_finetune(model, diag, library, train, test, 20, 1e-10, PARAMS, serial(_finetune(train, [])), "round1")
    assert fj.verdict == UNEXPLAINED and fj.named == [] and fj.model is None
    (trial,) = [t for t in fj.trials if t.kind == "LinearDamping"]
    assert not trial.accepted and abs(trial.values["coef"]) < 0.01


def _phased_finding(phases):
    amp = 1.5
    coef = [v for p in phases for v in (amp * math.cos(p), amp * math.sin(p))]
    return Finding(
        target=1,
        label="dv/dt: PeriodicForcing(ω=3.1, a phase per recording)",
        kind="PeriodicForcing",
        coef=coef,
        interval=[],
        gain=0.5,
        explained_rms=1.0,
        alone=0.5,
        inclusion=1.0,
        threshold=0.1,
        accepted=True,
        reason="",
        effect={},
    )


def test_a_drive_with_agreeing_phases_is_tried_with_one_shared_phase():
    agree = _phased_finding([0.30 + 0.01 * k for k in range(10)])
    scattered = _phased_finding(torch.linspace(0, 2 * math.pi, 11)[:-1].tolist())
    (a, b), r = shared_phase(agree)
    assert (
        r > 0.99
        and math.atan2(b, a) == pytest.approx(0.345, abs=1e-3)
        and math.hypot(a, b) == pytest.approx(1.5, rel=0.01)
    )
    assert shared_phase(scattered)[1] < 0.01 < PHASES_AGREE
    library = [Candidate("PeriodicForcing", None, {"omega": 3.1, "phased": True})]
    for finding, expected in ((agree, ["dv/dt: PeriodicForcing(ω=3.1)"]), (scattered, [])):
        diag = Diagnosis([finding], ["x", "v"], [], [], [], {}, {}, [])
        found, notes = finetune_candidates(diag, library, DiagnoseParams())
        assert [label for *_, label in found] == expected
        assert len(notes) == 1 and ("agree" in notes[0] if expected else "disagree" in notes[0])


@pytest.mark.slow  # a whole residual-loop run: `pytest -m slow` (.ci/run runs it)
def test_what_a_named_candidate_leaves_must_have_no_structure_the_screen_sees(damped):
    # a network's approximation error is invisible in null data (its own simulation), so a true effect can leave
    # more than 1 − min_explained of the control's excess; it is named only if the screen of its finetuned model
    # finds nothing structured left. Here min_explained > 1 makes every candidate "partial".
    train, test, model, (diag, library) = damped
    params = DiagnoseParams(n_boot=20, min_explained=1.5)
    calls: list[int] = []

    def clean(m):  # the screen of the finetuned model, as the loop runs it
        calls.append(1)
        return screen(m, train, params, 0)

    done: dict[str, tuple] = {}
    fresh = _finetune(train, [])

    def finetune(m, tag):  # the three judgements below finetune the same models: each is finetuned once
        if tag not in done:
            done[tag] = fresh(m, tag)
        return copy.deepcopy(done[tag][0]), done[tag][1]

    args = (model, diag, library, train, test, 20, 1e-10, params, serial(finetune), "round1")
    named = judge_by_finetune(*args, rescreen=clean)
    assert named.verdict == EFFECTS_NAMED and calls == [1] and named.rest is not None
    assert "finds no structure" in named.named[0].reason
    still = judge_by_finetune(*args, rescreen=lambda m: (diag, library))  # as if the damping were still there
    assert still.verdict == UNEXPLAINED and "still finds domega/dt: LinearDamping(omega)" in still.trials[0].reason
    assert judge_by_finetune(*args).verdict == UNEXPLAINED  # without a screen to ask, a partial fit is not named
