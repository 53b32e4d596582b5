"""The screen's confirmation through the model's integration of a step (`mpsim.diagnose.refit`).

A screened effect with whose coefficients the model's one-step integration fails (issue 71, item 5: a coefficient
run off to −3.6e12) is that effect's failure; it must not turn every other effect into an "echo" of it (with no
finite step left to regress on, their coefficients "fell to 0" and they were dropped).
"""

from __future__ import annotations

from mpsim.diagnose.loop import screen
from mpsim.diagnose.nuisance import nuisance_columns
from mpsim.diagnose.params import DiagnoseParams
from mpsim.diagnose.refit import confirm_by_integration
from tests.diagnose.test_heldout import nominal, pendulum

RUN_OFF = -3.6e12  # −c·θ³ with c = −3.6e12 blows up within a microsecond
CUBIC = "domega/dt: CubicStiffness(theta)"
PARAMS = DiagnoseParams(n_boot=20, kinds=["LinearDamping", "CubicStiffness"])


def test_an_effect_whose_step_fails_is_rejected_and_the_others_are_kept():
    data = pendulum(14, seed=0)
    model = nominal(data)
    diag, library = screen(model, data, PARAMS, 0)
    (damping,) = diag.accepted
    (cubic,) = [f for f in diag.findings if f.label == CUBIC]
    cubic.coef, cubic.gain, cubic.accepted = [RUN_OFF], 1.0, True  # the strongest: added to the model first
    base, _ = nuisance_columns(model, data, ())
    assert not confirm_by_integration(diag, library, model, data, base, PARAMS.min_gain)
    assert not cubic.accepted and cubic.reason.startswith("failed: with its coefficients -3.6e+12")
    assert damping.accepted  # before the fix: dropped as "an echo" of the cubic
    assert confirm_by_integration(diag, library, model, data, base, PARAMS.min_gain)  # the rest, checked again
    assert damping.accepted
