"""Unmeasured states in multi-step prediction (`mpsim.diagnose.latent`): each window's latent start, fitted.

The case: a driven mass measured by its position only (`tests/diagnose/latent_case.py`); here without Coulomb
friction, so the nominal model is the truth and the fitted velocity can be checked against the simulated one.
"""

from __future__ import annotations

import math

import pytest
import torch

from mpsim.diagnose.latent import fitted_latent, initial_latent, latent_jacobian, profile_out
from mpsim.diagnose.shooting import own_parameters, shooting_fit, window_error
from mpsim.diagnose.windows import window_starts
from tests.diagnose.latent_case import VISCOUS, measured, nominal_model, simulate


@pytest.fixture(scope="module")
def clean():
    """(data: q measured, v estimated; [S, T] the true velocity) of 8 one-second segments without friction."""
    _, _, v, _ = simulate(8, 0.0, seed=1)
    return measured(8, 0.0, seed=1), torch.as_tensor(v)


def _start_error(latent, model, v, length):  # v: [S, T] true velocity
    starts = window_starts(v.shape[1], length)
    return float((latent.raw(model)[..., 0, 0] - v[:, starts]).abs().max())


def test_the_fitted_latent_start_recovers_the_true_velocity(clean):
    data, v = clean
    model = nominal_model(data)
    for length in (100, 40):  # the whole segment; windows of 40, 40 and 20 steps
        estimate = initial_latent(model, data, length)
        fitted = fitted_latent(model, data, length)
        assert (
            estimate is not None and fitted is not None and fitted.z.shape == (8, len(window_starts(101, length)), 1, 1)
        )
        # the smoothed derivative is off by ~1e-3 at a segment's edge; the start that fits q is off by ~1e-5
        assert _start_error(estimate, model, v, length) > 5e-4
        assert _start_error(fitted, model, v, length) < 1e-4


def test_held_out_errors_do_not_depend_on_the_estimate_of_the_latent_state(clean):
    data, _ = clean
    model = nominal_model(data)
    x = data.x.clone()
    x[..., 1] += 0.05  # an estimate 20 % of v's spread off everywhere
    biased = type(data)(t=data.t, x=x, edge_index=data.edge_index, u=data.u, meta=data.meta)
    for length in (100, 40):
        e_clean, e_biased = window_error(model, data, length), window_error(model, biased, length)
        assert float(e_biased.mean()) < 2e-9  # at the noise level (normalised MSE of 2 µm on 8 cm)
        assert torch.allclose(e_clean, e_biased, rtol=1e-3, atol=1e-12)
    everything = type(data)(t=data.t, x=x, edge_index=data.edge_index, u=data.u, meta={**data.meta, "observed": None})
    assert float(window_error(model, everything, 100).mean()) > 0.01  # were v measured, its bias would count


def test_shooting_fits_the_parameters_jointly_with_every_windows_latent_start(clean):
    data, v = clean
    model = nominal_model(data)
    model.raw["c"].data.fill_(math.log(2 * VISCOUS))  # viscous friction twice the truth (positive: log space)
    fit = shooting_fit(model, data, 40, own_parameters(model), iters=25)
    fitted = {k: v.detach() for k, v in model.parameters_now().items()}
    assert fit.converged and float(fitted["c"]) == pytest.approx(VISCOUS, rel=0.01)
    assert float(fitted["m"]) == pytest.approx(1.0, rel=0.005)
    assert all(0 < se < 0.01 for se in fit.stderr)  # intervals of log c, log m with the starts profiled out
    assert fit.latent is not None and fit.latent.shape == (8, 3, 1, 1)
    assert float((fit.latent[..., 0, 0] - v[:, [0, 40, 80]]).abs().max()) < 2e-4


def test_the_latent_directions_are_projected_out_of_the_parameters_jacobian(clean):
    data, _ = clean
    model = nominal_model(data)
    latent = fitted_latent(model, data, 40)
    jac_z = latent_jacobian(model, data, latent)  # [B, K, M, 1]
    assert jac_z.shape[:2] == (8, 3) and float(jac_z.abs().max()) > 0
    jac = torch.randn(*jac_z.shape[:3], 2, dtype=jac_z.dtype)
    projected = profile_out(jac, jac_z)
    assert float((jac_z.mT @ projected).abs().max()) < 1e-8 * float(jac.abs().max() * jac_z.abs().max())


def test_a_drive_with_a_phase_per_recording_keeps_its_records_in_order(clean):
    """A term that reads the record's place in the batch (a drive with one phase per recording) cannot be rolled
    out with the records tiled for the difference steps: each set is rolled out in the records' order."""
    from mpsim.diagnose.library import PhasedDrive
    from mpsim.diagnose.shooting import with_effect

    data, v = clean
    phases = torch.linspace(0.0, 3.0, len(data)).tolist()
    drive = PhasedDrive(0.05, omega=2.0, phases=phases, target="v").bind(["q", "v"])
    model = with_effect(nominal_model(data), drive)
    fitted = fitted_latent(model, data, 40)
    assert fitted is not None and torch.isfinite(fitted.z).all()
    assert float(window_error(model, data, 40).max()) < math.inf
