"""Residual loop, case 3 (issue 4): Lorenz1 with a cubic term that S-MNN discovery's degree-2 library lacks.

The data carry dx/dt += −c·x³ (c = 0.005, `CubicStiffness` on x). A degree-2 discovery cannot express it; the
residual loop projects out every polynomial of degree ≤ 2 (what the model can already express), names the
cubic term on x, and a rediscovery with `extra_terms=["x^3"]` recovers all coefficients and removes the residual.
The fast tests take the discovered coefficients as given (the truth); the slow one trains both discoveries
through the command line, as `cli/smnn_residual.sh` does.
"""

from __future__ import annotations

import json

import pytest
import torch

from mpsim.data.dataset import fit_normalisation
from mpsim.data.trajectories import Inputs
from mpsim.diagnose.residual import one_step_residual
from mpsim.diagnose.search import find_effects
from mpsim.effects import CubicStiffness
from mpsim.models.smnn_discovery import SMNNDiscovery
from mpsim.solvers import ODESolver
from mpsim.systems.lorenz import CoupledLorenz
from tests.helpers import run_cli

C_TRUE = 0.005
LORENZ = {
    ("x", "x"): -10.0,
    ("x", "y"): 10.0,
    ("y", "x"): 28.0,
    ("y", "y"): -1.0,
    ("y", "x z"): -1.0,
    ("z", "z"): -8.0 / 3.0,
    ("z", "x y"): 1.0,
}


@pytest.fixture(scope="module")
def cubic_data():
    system = CoupledLorenz(
        name="lorenz1", n_nodes=1, ic_range=(-15.0, 15.0), effects=[CubicStiffness(C_TRUE, target="x")]
    )
    return system.generate(24, seed=0, dt=0.01, horizon=200)


def discovered(data, extra_terms=(), cubic=0.0) -> SMNNDiscovery:
    """A discovery model whose coefficients are the Lorenz ones (what a converged degree-2 run finds on clean
    data), plus `cubic` on x^3 in dx/dt when the library has it."""
    model = SMNNDiscovery(3, extra_terms=extra_terms, solver=ODESolver("dopri5", rtol=1e-8, atol=1e-8)).double()
    model.bind_effects(data.state_names)
    model.set_normalisation(*fit_normalisation(data))
    names = [model.monomial(term) for term in model.terms]
    with torch.no_grad():  # before training the coefficients are θ itself (identity preconditioner)
        model.theta.zero_()
        for (eq, term), value in LORENZ.items():
            model.theta[names.index(term), "xyz".index(eq)] = value
        if extra_terms:
            model.theta[names.index("x^3"), 0] = -cubic
    return model


def test_model_declares_what_it_can_express_and_steps_from_one_state(cubic_data):
    model = discovered(cubic_data)
    assert model.context_steps == 1 and model.represents_polynomials == 2
    assert "CubicStiffness" not in model.represents
    assert SMNNDiscovery(3, degree=3).represents_polynomials == 3
    # one batched solve over every step equals stepping each observed state with the rollout
    x, t = cubic_data.x[:2, :6], cubic_data.t[:6]
    steps = model.one_step(x, t, Inputs(cubic_data.edge_index))
    ref = torch.stack([model.rollout(x[:, k], t[k : k + 2], Inputs(cubic_data.edge_index))[:, 1] for k in range(5)], 1)
    assert steps.shape == (2, 5, 1, 3) and torch.allclose(steps, ref, atol=1e-6)


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_residual_names_the_missing_cubic_term(cubic_data):
    model = discovered(cubic_data)
    before = one_step_residual(model, cubic_data).r.var(dim=(0, 1, 2))
    diag = find_effects(model, cubic_data, n_boot=20)
    (found,) = diag.accepted  # nothing else: the y and z residuals are echoes of x's, and are refuted
    assert found.label == "dx/dt: CubicStiffness(x)" and found.target == 0
    # the regression on the step-averaged −x³ alone would be biased by (1 − σΔ/2) = 0.95 (within the step the
    # term's effect on x feeds back through ∂(dx/dt)/∂x = −σ); the loop refits it through the model's integration
    assert found.coef[0] == pytest.approx(C_TRUE, rel=0.01)
    assert found.effect == {
        "_target_": "mpsim.effects.CubicStiffness",
        "target": "x",
        "source": "x",
        "coef": found.coef[0],
    }
    # what the scientist does next: add the term the loop named to the library and rediscover (which fits the
    # windows themselves and recovers c without that bias: the slow test below)
    fixed = discovered(cubic_data, extra_terms=["x^3"], cubic=C_TRUE)
    after = one_step_residual(fixed, cubic_data).r.var(dim=(0, 1, 2))
    assert float(after[0]) < 1e-3 * float(before[0])
    assert find_effects(fixed, cubic_data, n_boot=20).accepted == []


def test_extra_terms_parse_resolve_and_threshold():
    model = SMNNDiscovery(3, extra_terms=["x^3", "x*y z", "y**2*z"])
    assert [model.monomial(t) for t in model.terms[-3:]] == ["x^3", "x y z", "y^2 z"]
    x = torch.tensor([2.0, -3.0, 5.0])
    assert model.library(x)[-3:].tolist() == [8.0, -30.0, 45.0]
    # names resolve against the data's state names when none were configured
    pend = SMNNDiscovery(2, extra_terms=["theta^3"])
    pend.bind_effects(["theta", "omega"])
    assert pend.terms[-1] == (0, 0, 0) and pend.report()["extra_terms"] == ["theta^3"]
    # an extra term's threshold is the coefficient of the same typical size as a linear term at the threshold
    model.set_normalisation(torch.zeros(3), torch.tensor([2.0, 4.0, 6.0]))
    thr = model.term_thresholds()
    assert torch.allclose(thr[:10], torch.full((10,), 0.1, dtype=thr.dtype))
    assert float(thr[10]) == pytest.approx(0.1 * 4.0 / 8.0)  # mean σ = 4, x^3 at σ = 8


@pytest.mark.parametrize(
    "terms, match",
    [
        (["x^2"], "already in the library"),
        (["w^3"], "not state variables"),
        (["x^0"], "cannot read"),
        (["x^3", "x x^2"], "listed twice"),
    ],
)
def test_bad_extra_terms_are_refused(terms, match):
    from mpsim.errors import ConfigError

    with pytest.raises(ConfigError, match=match):
        SMNNDiscovery(3, extra_terms=terms, state_names=["x", "y", "z"])


@pytest.mark.slow
def test_cli_discovery_diagnosis_and_rediscovery(tmp_path):
    """The whole case through the command line (a few minutes): degree-2 discovery on cubic data, the loop
    names CubicStiffness on x, rediscovery with x^3 in the library gets every coefficient within 2 % and a
    residual variance far below the first model's."""
    common = ["experiment=lorenz_cubic_discovery", "trainer.progress=false", f"paths.ckpt_dir={tmp_path}/ckpt"]
    run_cli(["train", *common, f"hydra.run.dir={tmp_path}/deg2"], tmp_path, timeout=1200, check=True)
    run_cli(
        ["diagnose", *common, "init=lorenz1_cubic.ckpt", "diagnose.n_boot=30", f"hydra.run.dir={tmp_path}/d2"],
        tmp_path,
        timeout=1200,
        check=True,
    )
    before = json.loads((tmp_path / "d2" / "diagnosis.json").read_text())
    # the cubic term on x and nothing else: the y-residual echoes of what the degree-2 x equation absorbed are
    # refuted once the loop's trial model carries the refit of the model's own coefficients
    assert before["verdict"] == "effects named"
    (found,) = before["effects_named"]
    assert found["label"] == "dx/dt: CubicStiffness(x)"
    # multiple-shooting fit with the discovered coefficients refit alongside: 6 % off (issue 11 bound: 10 %)
    assert found["values"]["coef"] == pytest.approx(C_TRUE, rel=0.10)

    run_cli(
        ["train", *common, "model.extra_terms=[x**3]", "system.name=lorenz1_cubic_x3", f"hydra.run.dir={tmp_path}/x3"],
        tmp_path,
        timeout=1200,
        check=True,
    )
    coefs = json.loads((tmp_path / "x3" / "summary.json").read_text())["model"]["coefficients"]
    for (eq, term), value in {**LORENZ, ("x", "x^3"): -C_TRUE}.items():
        assert coefs[eq][term] == pytest.approx(value, rel=0.02), (eq, term, coefs[eq])
    proc = run_cli(
        ["diagnose", *common, "init=lorenz1_cubic_x3.ckpt", "diagnose.n_boot=30", f"hydra.run.dir={tmp_path}/d3"],
        tmp_path,
        timeout=1200,
    )
    assert proc.returncode == 10, proc.stderr  # nothing missing
    after = json.loads((tmp_path / "d3" / "diagnosis.json").read_text())
    assert after["verdict"] == "nothing missing"
    rms_before, rms_after = before["screen"]["residual_rms"], after["screen"]["residual_rms"]
    assert rms_after[0] ** 2 < 1e-4 * rms_before[0] ** 2  # residual variance of x on the held-in data
    assert after["before"]["one_step_rmse"] < 0.01 * before["before"]["one_step_rmse"]  # held-out
