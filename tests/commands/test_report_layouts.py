"""`mpsim report layout=...` on synthetic run directories: Table 2, Table 1, learning curves, message size."""

import json
import shutil
from pathlib import Path

import pandas as pd
import pytest
import yaml

from mpsim.commands.report import run_report
from mpsim.errors import ConfigError


def _run(
    root: Path,
    name: str,
    *,
    system: str,
    mode: str = "scratch",
    model: str = "MPNODE",
    seed: int = 0,
    n_train: int = 100,
    errors: list[float] | None = None,
    message_size: int | None = 3,
    trained_on: str | None = None,
    best_val: float | None = None,
    overrides: list[str] = (),
    device: str | None = None,
    zero_messages: bool | None = None,
    per_step: list[float] | None = None,
    resolved: dict | None = None,
    model_config: dict | None = None,
    state_std: float | None = None,
    exported: str | None = None,
    init: str | None = None,
) -> Path:
    """A run directory as `mpsim train` (or a zero-shot run) leaves it: summary.json, metrics.csv, overrides."""
    run = root / name
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump([f"seed={seed}", *overrides]))
    config = {"_target_": f"mpsim.models.{model}"} | ({"message_size": message_size} if message_size else {})
    config |= {} if zero_messages is None else {"zero_messages": zero_messages}
    config |= model_config or {}
    if resolved is not None:  # the resolved config, as Hydra keeps it
        (run / ".hydra" / "config.yaml").write_text(yaml.safe_dump({"seed": seed} | resolved))
    summary = {
        "task": "train",
        "mode": mode,
        "status": "complete",
        "seed": seed,
        "system": {"name": system, "n_nodes": 10},
        "model": {"model": model, "config": config},
        "data": {"train": n_train, "val": 20, "test": 20, "n_times": 51},
    } | ({"device": device} if device else {})
    if errors is not None:  # a training run: per-epoch curve, Table 2 metric from it
        epochs = list(range(len(errors)))
        pd.DataFrame(
            {"epoch": epochs, "train_loss": [10 * e for e in errors], "val_error": errors, "test_error": errors}
        ).to_csv(run / "metrics.csv", index=False)
        best = min(range(1, len(errors)), key=lambda k: errors[k])
        summary |= {
            "min_test_error": errors[best],
            "min_test_error_epoch": best,
            "epochs_x_min_error": best * errors[best],
            "initial_test_error": errors[0],
            "epochs_run": len(errors) - 1,
            "best_val_error": best_val or errors[best],
            "test": {"rmse": errors[best]},
        }
    else:  # zero-shot evaluation: a test set, no training set
        summary["data"] = {"test": 20, "n_times": 51}
        summary |= {
            "task": "train",
            "mode": "zeroshot",
            "trained_on": trained_on,
            "test": {"rmse": best_val},
            "test_error": best_val,
        }
    summary |= {k: v for k, v in (("exported", exported), ("init", init)) if v is not None}
    if state_std is not None:  # a one-feature system whose states this run normalised by `state_std`
        summary["system"]["state_names"] = ["x"]
        summary["test"]["rmse_raw"] = summary["test"]["rmse"] * state_std
    if per_step is not None:  # test RMSE at each rollout step (index = step), as evaluation records it
        summary["test"]["per_step_rmse"] = per_step
    (run / "summary.json").write_text(json.dumps(summary))
    return run


def _report(cfg_factory, tmp_path, layout, runs, *extra):
    cfg = cfg_factory("report", f"layout={layout}", f"runs=[{runs}]", *extra)
    out = tmp_path / f"report_{layout}"
    return run_report(cfg, output_dir=out), out


@pytest.fixture
def table2_runs(tmp_path):
    root = tmp_path / "runs"
    _run(root, "pre", system="lorenz3", errors=[2.0, 1.0, 0.8])  # pre-training: not a Table 2 column
    for seed in (0, 1):
        for ds in (50, 100):
            _run(
                root,
                f"lf{seed}{ds}",
                system="lorenz10",
                mode="finetune",
                seed=seed,
                n_train=ds,
                errors=[1.0, 0.5, 0.4, 0.45, 0.5],
            )  # min 0.4 at epoch 2 → 0.8
            _run(
                root,
                f"ls{seed}{ds}",
                system="lorenz10",
                seed=seed,
                n_train=ds,
                errors=[2.0, 1.5, 1.0, 0.8, 0.6 + 0.1 * seed],
            )  # min at epoch 4 → 2.4 / 2.8
        _run(root, f"gf{seed}", system="gene_ba_large", mode="finetune", seed=seed, errors=[0.5, 0.2, 0.1])
        _run(root, f"gs{seed}", system="gene_ba_large", seed=seed, errors=[3.0, 1.0, 0.5])
        _run(
            root, f"gl{seed}", system="gene_ba_large", model="L2S", seed=seed, message_size=None, errors=[3.0, 2.0, 0.9]
        )
    return root


def test_table2_rows_columns_cells_and_orderings(cfg_factory, tmp_path, table2_runs):
    result, out = _report(cfg_factory, tmp_path, "table2", table2_runs)
    text = (out / "report.md").read_text()
    assert "| model | Lorenz10 ds=50 | Lorenz10 ds=100 | Gene |" in text  # lorenz3 pre-training is left out
    assert "| MP-NODE finetuned | 0.8 ± 0 | 0.8 ± 0 | 0.2 ± 0 |" in text
    assert "| MP-NODE scratch | 2.6 ± 0.28 | 2.6 ± 0.28 | 1 ± 0 |" in text
    assert "| L2S | N/A | N/A | 1.8 ± 0 |" in text
    assert "- Lorenz10 ds=50: finetuned < scratch (0.8 vs 2.6, 3.2×) — holds; seed by seed: in 2 of 2" in text
    assert "MP-NODE finetuned < L2S" in text
    assert "632.7" in text  # the paper's numbers are printed beside ours
    assert "`lorenz10`: 8 runs, 50/100 training trajectories, 50 steps, up to 4 epochs, seeds 0, 1" in text
    table = pd.read_csv(out / "report.csv")
    assert set(table["row"]) == {"MP-NODE finetuned", "MP-NODE scratch", "L2S"} and (table["runs"] == 2).all()
    assert (out / "table2.png").stat().st_size > 0 and (out / "runs.csv").is_file()
    assert result["n_runs"] == 15


def test_table2_says_in_how_many_seeds_an_ordering_holds(cfg_factory, tmp_path):
    root = tmp_path / "runs"
    # seed 0: finetuned 1 × 0.1 = 0.1 < scratch 0.4; seed 1: finetuned 0.6 > scratch 0.4; seed 2 ran only finetuned
    for seed, fine in ((0, [1.0, 0.1, 0.2]), (1, [1.0, 0.7, 0.3]), (2, [1.0, 0.1, 0.2])):
        _run(root, f"f{seed}", system="kuramoto10_er", mode="finetune", seed=seed, errors=fine)
    for seed in (0, 1):
        _run(root, f"s{seed}", system="kuramoto10_er", seed=seed, errors=[2.0, 0.5, 0.2])
    _, out = _report(cfg_factory, tmp_path, "table2", root)
    text = (out / "report.md").read_text()
    # the means say "holds" (0.267 vs 0.4); the seeds that ran both arms split
    assert "finetuned < scratch (0.2667 vs 0.4, 1.5×) — holds; seed by seed: in 1 of 2" in text


def test_table1_validation_test_and_zero_shot_columns(cfg_factory, tmp_path):
    root = tmp_path / "runs"
    for seed in (0, 1):
        _run(root, f"mp{seed}", system="gene_ba_small", seed=seed, errors=[1.0, 0.1, 0.05], best_val=0.06)
        _run(root, f"er{seed}", system="gene_er_small", trained_on="gene_ba_small", best_val=0.07 + 0.02 * seed)
        _run(root, f"ws{seed}", system="gene_ws_small", trained_on="gene_ba_small", best_val=0.9)
    _run(root, "l2s", system="gene_ba_small", model="L2S", message_size=None, errors=[1.0, 0.3, 0.2], best_val=0.25)
    _, out = _report(cfg_factory, tmp_path, "table1", root)
    text = (out / "report.md").read_text()
    assert "| model | Validation BA | Test BA | Test ER (unseen) | Test WS (unseen) |" in text
    assert "| MP-NODE | 0.06 ± 0 | 0.05 ± 0 | 0.08 ± 0.014 | 0.9 ± 0 |" in text
    assert "| L2S | 0.25 | 0.2 | N/A | N/A |" in text
    assert "Test ER (unseen): 1.6× the error on BA test data — same order" in text
    assert "Test WS (unseen): 18× the error on BA test data — NOT the same order" in text
    assert "validation: MP-NODE 0.06 < L2S 0.25 — holds" in text
    assert "0.0051 ± 0.0001" in text and (out / "table1.png").is_file()
    # runs that recorded no per-step errors (from before they were kept): no horizon section
    assert "Zero-shot by rollout horizon" not in text and not (out / "table1_horizons.png").exists()


def test_table1_zero_shot_ratio_by_rollout_step(cfg_factory, tmp_path):
    root = tmp_path / "runs"
    ba = [0.01 * k for k in range(11)]  # 10 steps: the listed steps are 1, 2, 5, 10
    er = [e * (0.8 if k <= 2 else 2.0) for k, e in enumerate(ba)]  # easier early, harder late
    for seed in (0, 1):
        _run(root, f"mp{seed}", system="gene_ba_small", seed=seed, errors=[1.0, 0.1, 0.05], per_step=ba)
        _run(root, f"er{seed}", system="gene_er_small", trained_on="gene_ba_small", best_val=0.1, per_step=er)
        _run(
            root,
            f"ws{seed}",
            system="gene_ws_small",
            trained_on="gene_ba_small",
            best_val=0.02,
            per_step=[0.8 * e for e in ba],
        )
    _, out = _report(cfg_factory, tmp_path, "table1", root)
    text = (out / "report.md").read_text()
    assert "| ratio by rollout step | 1 | 2 | 5 | 10 | paper (full horizon) |" in text
    assert "| MP-NODE: BA test RMSE | 0.01 | 0.02 | 0.05 | 0.1 |  |" in text
    assert "| MP-NODE: ER / BA | 0.80 | 0.80 | 2.00 | 2.00 | 0.58 |" in text
    assert "| MP-NODE: WS / BA | 0.80 | 0.80 | 0.80 | 0.80 | 0.51 |" in text
    assert "- MP-NODE on ER (unseen): easier than BA at steps 1–2, harder at steps 5–10" in text
    assert "- MP-NODE on WS (unseen): easier than BA at every listed step (the paper's direction)" in text
    assert (out / "table1_horizons.png").is_file()
    # a model whose training runs recorded no per-step errors gets no ratio rows (not ratios of nothing)
    _run(root, "l2s", system="gene_ba_small", model="L2S", message_size=None, errors=[1.0, 0.3, 0.2])
    _run(root, "l2s_er", system="gene_er_small", model="L2S", trained_on="gene_ba_small", best_val=0.3, per_step=er)
    _, out = _report(cfg_factory, tmp_path / "again", "table1", root)
    text = (out / "report.md").read_text()
    assert "| MP-NODE: ER / BA | 0.80 | 0.80 | 2.00 | 2.00 | 0.58 |" in text
    assert "L2S: ER / BA" not in text and "L2S: BA test RMSE" not in text


def test_curves_overlay_finetune_and_scratch(cfg_factory, tmp_path, table2_runs):
    _, out = _report(cfg_factory, tmp_path, "curves", table2_runs)
    text = (out / "report.md").read_text()
    assert "**lorenz10, ds=50** — target: 0.65" in text  # scratch's mean minimum (0.6 and 0.7)
    assert "| MP-NODE finetuned | 1 | 1 | 0.4 @ 2 |" in text  # reaches 0.65 at epoch 1 (0.5)
    assert "| MP-NODE scratch | 2 | 4 | 0.65 @ 4 |" in text
    curves = pd.read_csv(out / "report.csv")
    assert {"system", "n_train", "row", "epoch", "test_error_mean"} <= set(curves.columns)
    assert (out / "curves.png").stat().st_size > 0


def test_message_size_layout(cfg_factory, tmp_path):
    root = tmp_path / "runs"
    for m, err in ((1, 0.9), (3, 0.5), (7, 0.3), (13, 0.29)):
        for seed in (0, 1):
            _run(
                root,
                f"k{m}_{seed}",
                system="kuramoto10_ba",
                seed=seed,
                message_size=m,
                errors=[2.0, 1.0, err + 0.01 * seed],
            )
    _run(root, "l2s", system="kuramoto10_ba", model="L2S", message_size=None, errors=[2.0, 1.0, 0.6])
    _run(root, "zs", system="kuramoto10_ba", message_size=7, trained_on="kuramoto10_er", best_val=0.1)  # not trained
    _, out = _report(cfg_factory, tmp_path, "message_size", root)
    text = (out / "report.md").read_text()
    assert "| 7 | 2 | 0.305 ± 0.0071 |" in text
    assert "| L2S | 1 | 0.6 | 6 | 1.2 |" in text  # L2S's final train loss and epochs_x_min_error too (epoch 2 × 0.6)
    table = pd.read_csv(out / "report.csv")
    assert list(table.dropna(subset=["message_size"])["message_size"].astype(int)) == [1, 3, 7, 13]
    assert (out / "message_size.png").is_file() and (out / "message_size_curves.png").is_file()


def test_message_size_layout_compares_runs_at_matched_epochs(cfg_factory, tmp_path):
    root = tmp_path / "runs"
    # 8 epochs: m = 1 leads until epoch 4, m = 7 from epoch 6 on; m = 13 stopped after epoch 4
    _run(root, "m1", system="kuramoto10_ba", message_size=1, errors=[2, 0.5, 0.4, 0.4, 0.4, 0.4, 0.4, 0.4, 0.4])
    for seed, late in ((0, 0.2), (1, 0.3)):
        errors = [2, 0.9, 0.8, 0.7, 0.6, 0.5, late, 0.9, 0.9]  # a rise after the minimum keeps the minimum so far
        _run(root, f"m7_{seed}", system="kuramoto10_ba", seed=seed, message_size=7, errors=errors)
    _run(root, "m13", system="kuramoto10_ba", message_size=13, errors=[2, 0.6, 0.5, 0.45, 0.3])
    l2s = [2, 0.7, 0.7, 0.7, 0.7, 0.7, 0.7, 0.7, 0.65, 0.1, 0.1, 0.1, 0.1]  # longer than MP-NODE (as 10000 vs 4000)
    _run(root, "l2s", system="kuramoto10_ba", model="L2S", message_size=None, errors=l2s)
    _, out = _report(cfg_factory, tmp_path, "message_size", root)
    text = (out / "report.md").read_text()
    assert "| message size | by epoch 2 | by epoch 4 | by epoch 6 | by epoch 8 |" in text
    assert "| 1 | 0.4 | 0.4 | 0.4 | 0.4 |" in text
    assert "| 7 | 0.8 ± 0 | 0.6 ± 0 | 0.25 ± 0.071 | 0.25 ± 0.071 |" in text
    assert "| 13 | 0.5 | 0.3 | – | – |" in text
    assert "| L2S | 0.7 | 0.7 | 0.7 | 0.65 |" in text  # at MP-NODE's epochs, not the quarters of its own 12


@pytest.fixture
def saved_figures(monkeypatch):
    """The figures a layout saves, by file name, kept open instead of written."""
    from mpsim.commands import report_layouts

    saved = {}

    def keep(fig, path):
        saved[path.name] = fig
        return path

    monkeypatch.setattr(report_layouts, "save_figure", keep)
    return saved


def test_message_size_figure_does_not_magnify_a_few_percent(cfg_factory, tmp_path, saved_figures):
    # Figure 7's three message sizes ended 4 % apart; the report's panel must show them on at least a factor 4
    root = tmp_path / "runs"
    for m, err in ((7, 0.148), (13, 0.142), (20, 0.146)):
        _run(root, f"m{m}", system="quad3", message_size=m, errors=[1.0, 0.5, err])
    _report(cfg_factory, tmp_path, "message_size", root)
    fig = saved_figures["message_size.png"]
    lo, hi = fig.axes[0].get_ylim()
    assert hi / lo == pytest.approx(4.0) and lo < 0.142 and 0.148 < hi


def test_message_size_curves_name_l2s_in_both_panels(cfg_factory, tmp_path, saved_figures):
    # the curves figure drew L2S's test error unnamed and left its train loss out
    root = tmp_path / "runs"
    _run(root, "m7", system="quad3", message_size=7, errors=[1.0, 0.5, 0.3])
    for seed in (0, 1):
        _run(root, f"l2s{seed}", system="quad3", model="L2S", seed=seed, message_size=None, errors=[1.0, 0.4, 0.2])
    _report(cfg_factory, tmp_path, "message_size", root)
    train_ax, test_ax = saved_figures["message_size_curves.png"].axes
    for ax in (train_ax, test_ax):
        dashed = [line for line in ax.get_lines() if line.get_linestyle() == "--"]
        assert len(dashed) == 2  # one per L2S seed
    assert [t.get_text() for t in train_ax.get_legend().get_texts()] == ["m=7", "L2S"]
    assert list(train_ax.get_lines()[-1].get_ydata()) == [10.0, 4.0, 2.0]  # train loss is 10x the error (see _run)


def test_messages_layout_compares_messages_on_and_off(cfg_factory, tmp_path):
    root = tmp_path / "runs"
    for seed in (0, 1):  # train loss is 10× the error (see _run)
        errors = [3, 1, 0.8, 0.5, 0.2 + 0.1 * seed]
        _run(root, f"on{seed}", system="pendulum2", seed=seed, zero_messages=False, errors=errors)
    _run(root, "off", system="pendulum2", zero_messages=True, errors=[3, 1, 0.9, 0.9, 0.9])
    _run(root, "old", system="pendulum2", seed=2, errors=[3, 1, 0.6, 0.4, 0.3])  # no flag recorded: messages on
    _run(root, "l2s", system="pendulum2", model="L2S", message_size=None, errors=[3, 0.1, 0.1, 0.1, 0.1])  # not MP-NODE
    _run(root, "zs", system="pendulum2", zero_messages=False, trained_on="pendulum2", best_val=0.1)  # trains nothing
    _, out = _report(cfg_factory, tmp_path, "messages", root)
    text = (out / "report.md").read_text()
    assert "| on | 3 | 2.67 ± 0.58 | 0.267 ± 0.058 | 1.067 ± 0.23 |" in text  # 0.2, 0.3 and the old run's 0.3
    assert "| off (`zero_messages=true`) | 1 | 9 | 0.9 | 1.8 |" in text
    assert "Messages off / on: train loss 3.38×, test error 3.38× — messages lower both" in text
    assert "| messages | by epoch 1 | by epoch 2 | by epoch 3 | by epoch 4 |" in text
    assert "| on | 10 ± 0 | 7.33 ± 1.2 | 4.67 ± 0.58 | 2.67 ± 0.58 |" in text
    assert "| off (`zero_messages=true`) | 10 | 9 | 9 | 9 |" in text
    table = pd.read_csv(out / "report.csv")
    assert list(table["messages"]) == ["on", "off"] and list(table["runs"]) == [3, 1]
    assert (out / "messages.png").is_file()


def test_messages_layout_says_when_messages_do_not_help(cfg_factory, tmp_path):
    root = tmp_path / "runs"
    _run(root, "on", system="kuramoto10_ba", zero_messages=False, errors=[3, 1, 0.9])
    _run(root, "off", system="kuramoto10_ba", zero_messages=True, errors=[3, 1, 0.5])
    _, out = _report(cfg_factory, tmp_path, "messages", root)
    assert "test error 0.556× — messages do NOT lower both" in (out / "report.md").read_text()


def test_the_settings_caption_says_where_the_runs_ran(cfg_factory, tmp_path):
    root = tmp_path / "runs"
    for seed, device in ((0, "cpu (1 thread)"), (1, "cpu (1 thread)"), (2, "cuda:0 (NVIDIA H100 80GB HBM3)")):
        _run(root, f"k{seed}", system="kuramoto10_ba", seed=seed, errors=[2.0, 1.0, 0.5], device=device)
    _run(root, "old", system="lorenz10", errors=[2.0, 1.0, 0.5])  # a summary from before `device` was kept
    _run(root, "old3", system="kuramoto10_ba", seed=3, errors=[2.0, 1.0, 0.5])
    _, out = _report(cfg_factory, tmp_path, "message_size", root)
    text = (out / "report.md").read_text()
    assert (
        "seeds 0, 1, 2, 3, on cpu (1 thread) ×2 / cuda:0 (NVIDIA H100 80GB HBM3) ×1 (device not recorded for 1)" in text
    )
    assert "- `lorenz10`: 1 run, 100 training trajectories, 50 steps, up to 2 epochs, seed 0\n" in text


def test_runs_with_other_settings_are_kept_apart_not_averaged_as_seeds(cfg_factory, tmp_path):
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
        _run(
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
    _run(root, "nr", system="gene_ba_large", mode="finetune", errors=[1.0, 0.1], resolved=no_refit, state_std=9.4)
    # a key an older mpsim did not write counts only where the runs that have it disagree
    _run(root, "s0", system="gene_ba_large", errors=[2.0, 0.8], resolved={"trainer": {"lr": 1e-3}}, state_std=13.8)
    _run(root, "s1", system="gene_ba_large", seed=1, errors=[2.0, 0.6], state_std=13.8)
    _, out = _report(cfg_factory, tmp_path, "table2", root)
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
    _, out = _report(cfg_factory, tmp_path / "curves", "curves", root)
    text = (out / "report.md").read_text()
    # the curves compared in raw units: each run's normalised error × its own state std
    assert "target: 9.66, the best mean test error every curve reaches" in text
    assert "| MP-NODE finetuned (mode.refit_normalisation=false) | 9.4 | 1 | 0.94 @ 1 |" in text
    assert "| MP-NODE scratch | 27.6 | 1 | 9.66 @ 1 |" in text
    assert "Errors in raw units (each run's normalised error × its state std)" in text
    shutil.rmtree(root / "nr")  # the same normalisation everywhere: nothing to say about units
    _, out = _report(cfg_factory, tmp_path / "same", "table2", root)
    assert "Units:" not in (out / "report.md").read_text()
    _, out = _report(cfg_factory, tmp_path / "same_curves", "curves", root)
    text = (out / "report.md").read_text()
    assert "raw units" not in text and "| MP-NODE scratch | 2 | 1 | 0.7 @ 1 |" in text  # normalised, as recorded


def test_table1_keeps_a_model_variant_apart_in_every_column(cfg_factory, tmp_path):
    # Table 1 with the self-loop ablation beside it: the zero-shot runs know their model from the checkpoint,
    # as summary.json records it, so its unseen columns (and its ratios by rollout step) follow its own row
    root = tmp_path / "runs"
    for loops, ba, er, seeds in ((False, 0.1, 0.3, (0, 1)), (True, 0.05, 0.6, (0,))):
        for seed in seeds:
            model = {"model_config": {"self_loops": loops}, "seed": seed}
            _run(root, f"ba{loops}{seed}", system="gene_ba_small", errors=[1.0, ba], per_step=[0, ba, ba], **model)
            _run(
                root,
                f"er{loops}{seed}",
                system="gene_er_small",
                trained_on="gene_ba_small",
                best_val=er,
                per_step=[0, er, er],
                **model,
            )
    _, out = _report(cfg_factory, tmp_path, "table1", root)
    text = (out / "report.md").read_text()
    assert "| MP-NODE (model.self_loops=false) | 0.1 ± 0 | 0.1 ± 0 | 0.3 ± 0 |" in text
    assert "| MP-NODE (model.self_loops=true) | 0.05 | 0.05 | 0.6 |" in text
    assert "- MP-NODE (model.self_loops=true), Test ER (unseen): 12× the error on BA test data" in text
    assert "| MP-NODE (model.self_loops=false): ER / BA | 3.00 | 3.00 | 0.58 |" in text
    assert "| MP-NODE (model.self_loops=true): ER / BA | 12.00 | 12.00 | 0.58 |" in text


def test_zero_shot_runs_follow_the_training_run_of_the_checkpoint_they_evaluated(cfg_factory, tmp_path):
    # two models that differ only in how they were trained (the learning rate): a zero-shot run's own config does
    # not say it, the training run whose exported checkpoint it evaluated does
    root = tmp_path / "runs"
    for lr, er in ((0.001, 0.3), (0.0001, 0.6)):
        for seed in (0, 1):
            ckpt = f"/ckpts/lr{lr}_s{seed}.ckpt"
            trainer = {"trainer": {"lr": lr}}
            _run(
                root,
                f"ba{lr}_{seed}",
                system="gene_ba_small",
                seed=seed,
                errors=[1.0, 0.1],
                resolved=trainer,
                exported=ckpt,
            )
            _run(root, f"er{lr}_{seed}", system="gene_er_small", seed=seed, trained_on="gene_ba_small", best_val=er,
                 resolved={"trainer": {"lr": 0.001}}, init=ckpt)  # fmt: skip
    _, out = _report(cfg_factory, tmp_path, "table1", root)
    text = (out / "report.md").read_text()
    assert "| MP-NODE (trainer.lr=0.001) | 0.1 ± 0 | 0.1 ± 0 | 0.3 ± 0 |" in text
    assert "| MP-NODE (trainer.lr=0.0001) | 0.1 ± 0 | 0.1 ± 0 | 0.6 ± 0 |" in text
    assert "made_" not in pd.read_csv(out / "runs.csv").columns


@pytest.mark.parametrize("layout", ["table1", "table2", "curves", "message_size", "messages"])
def test_a_layout_over_zero_shot_runs_only_says_what_it_lacks(cfg_factory, tmp_path, layout):
    # the training run has not finished (no summary.json), its zero-shot runs have: no column a training run writes
    root = tmp_path / "runs"
    _run(root, "er", system="gene_er_small", trained_on="gene_ba_small", best_val=0.3)
    result, out = _report(cfg_factory, tmp_path, layout, root)
    assert result["n_runs"] == 1
    assert "- `gene_er_small`: 1 run, 50 steps, seed 0\n" in (out / "report.md").read_text()


@pytest.mark.parametrize("layout", ["table1", "table2", "curves", "message_size", "messages"])
def test_a_layout_over_other_tasks_summaries_finds_no_training_run(cfg_factory, tmp_path, layout):
    # a bench table and a simulated dataset beside the runs: summaries without a mode, model or training set
    for name, summary in (
        ("bench", {"task": "bench", "suite": "epoch_time", "rows": []}),
        ("sim", {"task": "simulate"}),
    ):
        (tmp_path / "runs" / name).mkdir(parents=True)
        (tmp_path / "runs" / name / "summary.json").write_text(json.dumps(summary))
    result, out = _report(cfg_factory, tmp_path, layout, tmp_path / "runs")
    assert result["n_runs"] == 2 and "training runs found." in (out / "report.md").read_text()


def test_unknown_layout_is_refused(cfg_factory, tmp_path, table2_runs):
    with pytest.raises(ConfigError, match="layout='table3' is unknown; choose one of table2, table1"):
        _report(cfg_factory, tmp_path, "table3", table2_runs)


def test_generic_report_is_unchanged_without_a_layout(cfg_factory, tmp_path, table2_runs):
    cfg = cfg_factory("report", f"runs=[{table2_runs}]")
    result = run_report(cfg, output_dir=tmp_path / "plain")
    assert "model_class" not in pd.read_csv(tmp_path / "plain" / "report.csv").columns
    assert result["n_runs"] == 15
