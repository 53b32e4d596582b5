"""Runs with other settings are kept apart, not averaged as seeds (`mpsim.report.variants`), and the settings caption
every layout report opens with."""

import shutil

import pandas as pd

from tests.report.fake_runs import fake_run, report_of


def test_the_settings_caption_says_where_the_runs_ran(tmp_path):
    root = tmp_path / "runs"
    for seed, device in ((0, "cpu (1 thread)"), (1, "cpu (1 thread)"), (2, "cuda:0 (NVIDIA H100 80GB HBM3)")):
        fake_run(root, f"k{seed}", system="kuramoto10_ba", seed=seed, errors=[2.0, 1.0, 0.5], device=device)
    fake_run(root, "old", system="lorenz10", errors=[2.0, 1.0, 0.5])  # a summary from before `device` was kept
    fake_run(root, "old3", system="kuramoto10_ba", seed=3, errors=[2.0, 1.0, 0.5])
    _, out = report_of(tmp_path, "message_size", root)
    text = (out / "report.md").read_text()
    assert (
        "seeds 0, 1, 2, 3, on cpu (1 thread) ×2 / cuda:0 (NVIDIA H100 80GB HBM3) ×1 (device not recorded for 1)" in text
    )
    assert "- `lorenz10`: 1 run, 100 training trajectories, 50 steps, up to 2 epochs, seed 0\n" in text


def test_runs_with_other_settings_are_kept_apart_not_averaged_as_seeds(tmp_path):
    root = tmp_path / "runs"
    for seed in (0, 1):  # two seeds of the refitted finetune, placed and shown differently (incidental keys)
        incidental = {
            "paths": {"output_root": f"/elsewhere/{seed}"},
            "device": ["cpu", "cuda"][seed],
            "threads": 1 + seed,
            "init": f"/pre/s{seed}.ckpt",
            "eval": {"plots": bool(seed)},
            "data": {"seed": seed, "n_val": 20},
        }
        config = incidental | {"mode": {"name": "finetune", "refit_normalisation": True}}
        fake_run(
            root,
            f"f{seed}",
            system="gene_ba_large",
            mode="finetune",
            seed=seed,
            errors=[1.0, 0.4],
            resolved=config,
            state_std=13.8,
        )
    no_refit = {"mode": {"name": "finetune", "refit_normalisation": False}, "data": {"n_val": 20}}
    fake_run(root, "nr", system="gene_ba_large", mode="finetune", errors=[1.0, 0.1], resolved=no_refit, state_std=9.4)
    # a key an older mpsim did not write counts only where the runs that have it disagree
    fake_run(root, "s0", system="gene_ba_large", errors=[2.0, 0.8], resolved={"trainer": {"lr": 1e-3}}, state_std=13.8)
    fake_run(root, "s1", system="gene_ba_large", seed=1, errors=[2.0, 0.6], state_std=13.8)
    _, out = report_of(tmp_path, "table2", root)
    text = (out / "report.md").read_text()
    assert "| MP-NODE finetuned (mode.refit_normalisation=true) | 0.4 ± 0 |" in text
    assert "| MP-NODE finetuned (mode.refit_normalisation=false) | 0.1 |" in text
    assert "| MP-NODE scratch | 0.7 ± 0.14 |" in text  # averaged: the seeds agree where both say
    assert (
        "- 3 runs (system gene_ba_large, model_class MPNODE, mode finetune, n_train 100) differ in "
        "`mode.refit_normalisation`: kept apart, not averaged as seeds" in text
    )
    # the paper's ordering, for each finetuned variant against scratch
    assert "- Gene: MP-NODE finetuned (mode.refit_normalisation=false) < MP-NODE scratch (0.1 vs 0.7, 7×)" in text
    assert "- Gene: MP-NODE finetuned (mode.refit_normalisation=true) < MP-NODE scratch (0.4 vs 0.7, 1.7×)" in text
    # the run that kept its pre-training's normalisation measures its errors in other units: said, with raw ones
    assert (
        "- Gene: the rows were normalised by different state stds (MP-NODE finetuned (mode.refit_normalisation=false)"
        " 9.4, MP-NODE finetuned (mode.refit_normalisation=true) 13.8, MP-NODE scratch 13.8)" in text
    )
    assert "test RMSE: MP-NODE finetuned (mode.refit_normalisation=false) 0.94, MP-NODE finetuned (" in text
    table = pd.read_csv(out / "report.csv")
    assert sorted(table["runs"]) == [1, 2, 2]
    _, out = report_of(tmp_path / "curves", "curves", root)
    text = (out / "report.md").read_text()
    # the curves compared in raw units: each run's normalised error × its own state std
    assert "target: 9.66, the best mean test error every curve reaches" in text
    assert "| MP-NODE finetuned (mode.refit_normalisation=false) | 9.4 | 1 | 0.94 @ 1 |" in text
    assert "| MP-NODE scratch | 27.6 | 1 | 9.66 @ 1 |" in text
    assert "Errors in raw units (each run's normalised error × its state std)" in text
    shutil.rmtree(root / "nr")  # the same normalisation everywhere: nothing to say about units
    _, out = report_of(tmp_path / "same", "table2", root)
    assert "Units:" not in (out / "report.md").read_text()
    _, out = report_of(tmp_path / "same_curves", "curves", root)
    text = (out / "report.md").read_text()
    assert "raw units" not in text and "| MP-NODE scratch | 2 | 1 | 0.7 @ 1 |" in text  # normalised, as recorded


def test_zero_shot_runs_follow_the_training_run_of_the_checkpoint_they_evaluated(tmp_path):
    # two models that differ only in how they were trained (the learning rate): a zero-shot run's own config does
    # not say it, the training run whose exported checkpoint it evaluated does
    root = tmp_path / "runs"
    for lr, er in ((0.001, 0.3), (0.0001, 0.6)):
        for seed in (0, 1):
            ckpt = f"/ckpts/lr{lr}_s{seed}.ckpt"
            trainer = {"trainer": {"lr": lr}}
            fake_run(
                root,
                f"ba{lr}_{seed}",
                system="gene_ba_small",
                seed=seed,
                errors=[1.0, 0.1],
                resolved=trainer,
                exported=ckpt,
            )
            fake_run(root, f"er{lr}_{seed}", system="gene_er_small", seed=seed, trained_on="gene_ba_small", best_val=er,
                 resolved={"trainer": {"lr": 0.001}}, init=ckpt)  # fmt: skip
    _, out = report_of(tmp_path, "table1", root)
    text = (out / "report.md").read_text()
    assert "| MP-NODE (trainer.lr=0.001) | 0.1 ± 0 | 0.1 ± 0 | 0.3 ± 0 |" in text
    assert "| MP-NODE (trainer.lr=0.0001) | 0.1 ± 0 | 0.1 ± 0 | 0.6 ± 0 |" in text
    assert "made_" not in pd.read_csv(out / "runs.csv").columns
