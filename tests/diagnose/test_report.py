"""The diagnosis report from the summary dict alone (`mpsim.diagnose.report`): diagnosis.md and the summary rows."""

import math
from pathlib import Path

from mpsim.diagnose.report import markdown, summary_rows, truth_text, values_text


def _summary(verdict: str, exit_code: int, one_step: float = 0.01) -> dict:
    """The smallest diagnosis.json a report is written from: nothing tested, screened or fixed."""
    return {
        "data": {"name": "pendulums", "n_heldin": 8, "n_heldout": 3},
        "init": "p.ckpt",
        "verdict": verdict,
        "verdict_note": "",
        "exit_code": exit_code,
        "effects_named": [],
        "judgement": {
            "horizon": 20,
            "error_given": 2e-3,
            "error_refit": 1e-3,
            "error_null": 1e-5,
            "error_final": 1e-3,
            "explained": 0.0,
            "notes": ["best candidate none"],
            "trials": [],
        },
        "finetuned": [],
        "screen": {
            "searched_rows": ["omega"],
            "state_names": ["theta", "omega"],
            "residual_rms": [0.1, 0.2],
            "null_rms": [0.01, 0.02],
            "null_level": [0.001, 0.002],
            "noise_std_estimate": [0.0, 0.0],
            "candidates_considered": [],
        },
        "rounds": [],
        "rejected_fixes": [],
        "fixed_effects": [],
        "before": {
            "one_step_rmse": one_step,
            "rollout_rmse": 0.5,
            "valid_prediction_time": 1.25,
            "horizons": {"5": {"t": 0.5, "rmse": 0.05}},
        },
        "after": None,
    }


def test_markdown_of_an_unexplained_verdict_shows_its_levels_and_an_empty_after_column():
    text = markdown(_summary("unexplained structured residual", 11))
    assert text.startswith("# mpsim diagnose: pendulums\n")
    assert "**Verdict: unexplained structured residual** (exit code 11)." in text
    assert "Windows of 20 steps. Model as given 0.002; its own parameters refit 0.001; null level 1e-05" in text
    assert "\n- best candidate none\n" in text
    assert "| (none tested) | | | | | | | |" in text
    assert "| omega | 0.2 | 0.02 | 0.002 | 0 |" in text
    assert "| one-step RMSE | 0.01 | - |" in text and "| rollout RMSE at 5 steps (t=0.5) | 0.05 | - |" in text
    assert "## Fix, round" not in text and "## Candidates finetuned" not in text and text.endswith("|\n")


def test_summary_rows_claim_nothing_without_a_named_effect_and_mark_a_diverged_rollout():
    rows = dict(summary_rows(_summary("unexplained structured residual", 11, math.nan), Path("run")))
    assert rows["verdict"] == "unexplained structured residual"
    assert rows["claim"] == "none: no candidate explains the structured residual"
    assert rows["held-out MSE"] == "given 0.002, own parameters refit 0.001, null level 1e-05"
    assert rows["one-step RMSE"] == "nan (diverged)" and rows["report"] == str(Path("run") / "diagnosis.md")
    assert "claim" not in dict(summary_rows(_summary("nothing missing", 10), Path("run")))


def test_values_and_truth_text():
    assert values_text({"coef": 0.2}, {"coef": (0.19, 0.21)}) == "coef 0.2 [0.19, 0.21]"
    truth = {"true": {"coef": 0.2}, "relative_error": {"coef": 0.01}}
    assert truth_text(truth) == "true coef 0.2, off by 1.0%"


def test_markdown_says_which_candidates_a_simpler_kind_stood_for():
    s = _summary("effects named", 0)
    note = "DryFriction(z) not considered: z never changes sign on these data (…): Bias covers it"
    s["screen"]["equivalent_forms"] = [note]
    assert f"not searched unless `diagnose.targets` names them).\n\n- {note}\n\n| state |" in markdown(s)
    assert "- DryFriction" not in markdown(_summary("effects named", 0))  # none: nothing said


def test_markdown_says_what_was_read_from_the_files():
    s = _summary("nothing missing", 10)
    s["data"]["covers"] = {"train": "a.csv 0–20 s", "val": "a.csv 20–25 s", "test": "a.csv 25–30 s"}
    s["data"]["accounts"] = [{
        "path": "recs/*.csv",
        "pattern": True,
        "segment": 1.0,
        "files": [
            {"file": "recs/a.csv", "rows": 301, "span": [0.0, 30.0], "gaps": [], "pieces": [
                {"piece": 1, "rows": 301, "span": [0.0, 30.0], "samples": 301, "segments": 30, "used": 301}]},
            {"file": "recs/b.csv", "rows": 6, "span": [0.0, 0.5], "gaps": [], "pieces": [
                {"piece": 1, "rows": 6, "span": [0.0, 0.5], "samples": 6, "segments": 0, "used": 0}]},
        ],
    }]  # fmt: skip
    text = markdown(s)
    assert "\n## Data\n\n- pattern recs/*.csv matched 2 files: a.csv, b.csv\n" in text
    assert "- b.csv: 6 rows, 0–0.5 s; not used: its 6 samples are shorter than one segment (1 s)\n" in text
    assert "- train: a.csv 0–20 s; val: a.csv 20–25 s; test: a.csv 25–30 s\n" in text
    assert "## Data" not in markdown(_summary("nothing missing", 10))  # simulated data: nothing to account for
