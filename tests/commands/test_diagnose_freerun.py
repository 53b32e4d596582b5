"""`mpsim diagnose` on measured data: the free run of the held-out records before and after, and the check that
keeps *nothing missing* from being claimed where the whole records drift (issue 71, items 4 and 8).

Data: the driven mass of `tests/diagnose/latent_case.py` (numpy RK4, q measured, v latent), 1 s segments; the
nominal model lacks the Coulomb friction. The held-out records are the segments themselves, free-run whole."""

from __future__ import annotations

from types import SimpleNamespace

from mpsim.commands.diagnose import FREE_RUN_NULL_FACTOR, drifts_beyond_null, free_run_before_after
from mpsim.commands.scoring import EvalOptions
from tests.diagnose.latent_case import COULOMB, NOISE, measured, nominal_model


def _check(coulomb: float):
    data = measured(6, coulomb, seed=1)
    model = nominal_model(data)
    job = SimpleNamespace(splits=SimpleNamespace(records=data), model=model, seed=0)
    result = SimpleNamespace(model=model, after=None, judgement=SimpleNamespace(model=model))
    result.diagnosis = SimpleNamespace(noise_std=[NOISE, 1e-3])
    options = EvalOptions(plots=False)
    freerun = free_run_before_after(job, result, options)  # type: ignore[arg-type]
    assert freerun is not None and len(freerun["rows"]) == 6 and all("after_rmse" not in r for r in freerun["rows"])
    return freerun, drifts_beyond_null(job, result, freerun, options)  # type: ignore[arg-type]


def test_a_model_without_the_friction_drifts_beyond_its_own_null_free_run():
    freerun, why = _check(COULOMB)
    assert why.startswith("not *nothing missing*") and f"needs ≤ {FREE_RUN_NULL_FACTOR:g}×" in why
    assert min(r["before_rmse"] for r in freerun["rows"]) > 0


def test_the_right_model_free_runs_as_its_own_simulation_does():
    _, why = _check(0.0)
    assert why == ""
