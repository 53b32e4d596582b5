"""`diagnose fix=true` on a `model=equations` spec writes `fixed.yaml` (issue 72, item 4): the spec with the named
effect written into its equations, which reads back with the fixed model's held-out error and trains as a plain
spec. Data: predator-prey with a constant inflow of prey (scorecard case i's spec, fewer recordings)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from tests.helpers import run_mpsim, run_mpsim_ok

CASES = Path(__file__).resolve().parents[2] / "examples" / "diagnose_cases"


@pytest.mark.slow  # three commands, a residual-loop run among them: `pytest -m slow` (.ci/run runs it)
def test_fix_writes_the_named_effect_into_the_spec_and_it_reads_back(tmp_path):
    bias = "system.effects=[{_target_: mpsim.effects.Bias, coef: 0.1, target: x}]"
    common = ["data.path=data/trajectories.npz", "paths.ckpt_dir=ck", "trainer.progress=false"]
    run_mpsim_ok(
        ["simulate", "system=equations", f"system.spec={CASES / 'i_bias_data.yaml'}", "system.name=i_bias", bias,
         "n=16", "format=npz", "hydra.run.dir=data"], tmp_path,
    )  # fmt: skip
    model = [f"model.spec={CASES / 'i_bias_model.yaml'}", "model=equations", "trainer=whitebox"]
    run_mpsim_ok(["train", *model, *common, "hydra.run.dir=train"], tmp_path)
    proc = run_mpsim(
        ["diagnose", "init=i_bias.ckpt", *common, "fix=true", "data.split=[0.6,0.15,0.25]", "diagnose.n_boot=10",
         "diagnose.kinds=[Bias,LinearDamping]", "hydra.run.dir=diag"], tmp_path,
    )  # fmt: skip
    assert proc.code == 0, proc.err[-2000:]
    out = json.loads((tmp_path / "diag" / "diagnosis.json").read_text())
    assert [e["kind"] for e in out["effects_named"]][:1] == ["Bias"]
    spec = yaml.safe_load((tmp_path / "diag" / "fixed.yaml").read_text())
    assert "bias_x" in spec["equations"]["x"] and spec["params"]["bias_x"] == pytest.approx(0.1, rel=0.1)
    assert "bias_x" in spec["learnable"]
    check = out["fixed_spec"]
    assert check["left_out"] == [] and check["heldout_mse"] == pytest.approx(check["fixed_model_heldout_mse"], rel=0.1)
    assert "fixed.yaml" in (tmp_path / "diag" / "diagnosis.md").read_text()
    run_mpsim_ok(
        ["train", "model=equations", "model.spec=diag/fixed.yaml", "trainer=whitebox", "trainer.max_epochs=2",
         *common, "hydra.run.dir=refit"], tmp_path,
    )  # fmt: skip
    refit = json.loads((tmp_path / "refit" / "summary.json").read_text())
    assert refit["model"]["physical_parameters"]["bias_x"] == pytest.approx(0.1, rel=0.1)
