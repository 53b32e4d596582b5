"""`layout=table1` (`mpsim.report.table1`) on synthetic run directories: validation, test and zero-shot columns, and
the zero-shot ratios by rollout step."""

from tests.report.fake_runs import fake_run, report_of


def test_table1_validation_test_and_zero_shot_columns(tmp_path):
    root = tmp_path / "runs"
    for seed in (0, 1):
        fake_run(root, f"mp{seed}", system="gene_ba_small", seed=seed, errors=[1.0, 0.1, 0.05], best_val=0.06)
        fake_run(root, f"er{seed}", system="gene_er_small", trained_on="gene_ba_small", best_val=0.07 + 0.02 * seed)
        fake_run(root, f"ws{seed}", system="gene_ws_small", trained_on="gene_ba_small", best_val=0.9)
    fake_run(root, "l2s", system="gene_ba_small", model="L2S", message_size=None, errors=[1.0, 0.3, 0.2], best_val=0.25)
    _, out = report_of(tmp_path, "table1", root)
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


def test_table1_zero_shot_ratio_by_rollout_step(tmp_path):
    root = tmp_path / "runs"
    ba = [0.01 * k for k in range(11)]  # 10 steps: the listed steps are 1, 2, 5, 10
    er = [e * (0.8 if k <= 2 else 2.0) for k, e in enumerate(ba)]  # easier early, harder late
    for seed in (0, 1):
        fake_run(root, f"mp{seed}", system="gene_ba_small", seed=seed, errors=[1.0, 0.1, 0.05], per_step=ba)
        fake_run(root, f"er{seed}", system="gene_er_small", trained_on="gene_ba_small", best_val=0.1, per_step=er)
        fake_run(
            root,
            f"ws{seed}",
            system="gene_ws_small",
            trained_on="gene_ba_small",
            best_val=0.02,
            per_step=[0.8 * e for e in ba],
        )
    _, out = report_of(tmp_path, "table1", root)
    text = (out / "report.md").read_text()
    assert "| ratio by rollout step | 1 | 2 | 5 | 10 | paper (full horizon) |" in text
    assert "| MP-NODE: BA test RMSE | 0.01 | 0.02 | 0.05 | 0.1 |  |" in text
    assert "| MP-NODE: ER / BA | 0.80 | 0.80 | 2.00 | 2.00 | 0.58 |" in text
    assert "| MP-NODE: WS / BA | 0.80 | 0.80 | 0.80 | 0.80 | 0.51 |" in text
    assert "- MP-NODE on ER (unseen): easier than BA at steps 1–2, harder at steps 5–10" in text
    assert "- MP-NODE on WS (unseen): easier than BA at every listed step (the paper's direction)" in text
    assert (out / "table1_horizons.png").is_file()
    # a model whose training runs recorded no per-step errors gets no ratio rows (not ratios of nothing)
    fake_run(root, "l2s", system="gene_ba_small", model="L2S", message_size=None, errors=[1.0, 0.3, 0.2])
    fake_run(root, "l2s_er", system="gene_er_small", model="L2S", trained_on="gene_ba_small", best_val=0.3, per_step=er)
    _, out = report_of(tmp_path / "again", "table1", root)
    text = (out / "report.md").read_text()
    assert "| MP-NODE: ER / BA | 0.80 | 0.80 | 2.00 | 2.00 | 0.58 |" in text
    assert "L2S: ER / BA" not in text and "L2S: BA test RMSE" not in text


def test_table1_keeps_a_model_variant_apart_in_every_column(tmp_path):
    # Table 1 with the self-loop ablation beside it: the zero-shot runs know their model from the checkpoint,
    # as summary.json records it, so its unseen columns (and its ratios by rollout step) follow its own row
    root = tmp_path / "runs"
    for loops, ba, er, seeds in ((False, 0.1, 0.3, (0, 1)), (True, 0.05, 0.6, (0,))):
        for seed in seeds:
            model = {"model_config": {"self_loops": loops}, "seed": seed}
            fake_run(root, f"ba{loops}{seed}", system="gene_ba_small", errors=[1.0, ba], per_step=[0, ba, ba], **model)
            fake_run(
                root,
                f"er{loops}{seed}",
                system="gene_er_small",
                trained_on="gene_ba_small",
                best_val=er,
                per_step=[0, er, er],
                **model,
            )
    _, out = report_of(tmp_path, "table1", root)
    text = (out / "report.md").read_text()
    assert "| MP-NODE (model.self_loops=false) | 0.1 ± 0 | 0.1 ± 0 | 0.3 ± 0 |" in text
    assert "| MP-NODE (model.self_loops=true) | 0.05 | 0.05 | 0.6 |" in text
    assert "- MP-NODE (model.self_loops=true), Test ER (unseen): 12× the error on BA test data" in text
    assert "| MP-NODE (model.self_loops=false): ER / BA | 3.00 | 3.00 | 0.58 |" in text
    assert "| MP-NODE (model.self_loops=true): ER / BA | 12.00 | 12.00 | 0.58 |" in text
