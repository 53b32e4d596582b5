"""Sweeps beyond the basic launcher: a 2-job sweep through submitit's local executor (the path a SLURM sweep
takes), and an Optuna search that minimises the value `mpsim train` returns (`objective=`)."""

from __future__ import annotations

import json

import pytest
import yaml

from tests.helpers import TINY_TRAIN, run_cli, run_mpsim_ok


def _jobs(root):
    return sorted(p.parent for p in root.rglob("summary.json"))


@pytest.mark.slow
@pytest.mark.scaling
def test_submitit_local_runs_a_two_job_sweep(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    proc = run_cli(
        ["train", "-m", "hydra/launcher=slurm_local", "seed=0,1", "eval.plots=false", *TINY_TRAIN], tmp_path, check=True
    )
    jobs = _jobs(tmp_path / "outputs" / "multirun")
    assert len(jobs) == 2, proc.stderr
    sweep = jobs[0].parent
    # each job ran in its own submitit process: submitit left one log folder per job id
    assert len(list((sweep / ".submitit").glob("*/*_result.pkl"))) == 2
    seeds = sorted(json.loads((j / "summary.json").read_text())["seed"] for j in jobs)
    assert seeds == [0, 1]


@pytest.mark.slow  # long; outside the default suite (<4 min on 2 cores), run by .ci/run's -m slow step
def test_optuna_search_minimises_the_objective(tmp_path):
    # in this process: the Optuna sweeper runs its trials with Hydra's basic launcher, one after another
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper")
    proc = run_mpsim_ok(
        [
            "train",
            "hparams_search=mpnode_lorenz10",
            "hydra.sweeper.n_trials=3",
            "system=lorenz3",
            "objective=final.val_error",
            "eval.plots=false",
            "trainer.max_epochs=2",
            *TINY_TRAIN,
        ],
        tmp_path,
    )
    jobs = _jobs(tmp_path / "outputs" / "multirun")
    assert len(jobs) == 3, proc.stderr
    summaries = [json.loads((j / "summary.json").read_text()) for j in jobs]
    values = [s["final"]["val_error"] for s in summaries]
    assert [s["objective"] for s in summaries] == [{"name": "final.val_error", "value": v} for v in values]
    result = yaml.safe_load((jobs[0].parent / "optimization_results.yaml").read_text())
    assert result["best_value"] == pytest.approx(min(values))  # Optuna saw each run's objective
    best = summaries[values.index(min(values))]
    assert result["best_params"]["model.hidden"] == best["model"]["config"]["hidden"]
    assert result["best_params"]["trainer.lr"] == pytest.approx(
        yaml.safe_load((jobs[values.index(min(values))] / ".hydra" / "config.yaml").read_text())["trainer"]["lr"]
    )


@pytest.mark.slow  # 8-25 s on 2 busy cores; the fast checks of the same path: tests/test_config.py (direction)
def test_hydra_sweeper_optuna_runs_a_search_as_hydra_documents_it(tmp_path):
    # Hydra's way: -m hydra/sweeper=optuna and a search space on the key (no hparams_search= file); the sweeper's
    # own default direction is an enum, Direction.minimize, which mpsim's check refused
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper")
    args = ["train", "-m", "hydra/sweeper=optuna", "hydra.sweeper.n_trials=2", "trainer.lr=interval(1e-3,1e-2)"]
    proc = run_mpsim_ok([*args, "system=lorenz3", "eval.plots=false", *TINY_TRAIN], tmp_path)
    jobs = _jobs(tmp_path / "outputs" / "multirun")
    assert len(jobs) == 2, proc.stderr
    values = [json.loads((j / "summary.json").read_text())["objective"]["value"] for j in jobs]
    result = yaml.safe_load((jobs[0].parent / "optimization_results.yaml").read_text())
    assert result["best_value"] == pytest.approx(min(values))
    assert 1e-3 <= result["best_params"]["trainer.lr"] <= 1e-2
    assert "2 runs under" in proc.stdout and "| trainer.lr |" in proc.stdout  # the search ends with its table
