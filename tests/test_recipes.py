"""The cli/ recipes' own options, checked with a stub `mpsim` (tests.helpers.run_recipe): what each queues and
reports, and one clear refusal for a bad option. (That the PAPER=1 recipes train what `bench=epoch_time` times is
tests/bench/test_epoch_time.py; the resumable-run helper is tests/test_recipe_lib.py.)"""

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from tests.helpers import run_recipe

pytestmark = pytest.mark.skipif(shutil.which("flock") is None, reason="the recipes need flock (util-linux)")


def _arg(call, key):
    return next(a.split("=", 1)[1] for a in call if a.startswith(key + "="))


def test_message_size_parts_kuramoto_trains_and_reports_only_figure_8(tmp_path):
    proc, calls = run_recipe("message_size.sh", tmp_path, PAPER="1", SEEDS="0", K_MSG="1,7,13", PARTS="kuramoto")
    assert proc.returncode == 0, proc.stderr
    trains = [c for c in calls if c[0] == "train"]
    # the recipe runs two trainings at a time (JOBS=2), so the stub logs them in the order they finish
    assert sorted((_arg(c, "system"), int(_arg(c, "model.message_size"))) for c in trains) == [
        ("kuramoto10_ba", 1),
        ("kuramoto10_ba", 7),
        ("kuramoto10_ba", 13),
    ]
    (report,) = [c for c in calls if c[0] == "report"]
    assert _arg(report, "runs") == f"[{tmp_path / 'message_size.sh' / 'kuramoto'}]"  # no folder that was not made


def test_message_size_default_runs_both_figures(tmp_path):
    proc, calls = run_recipe("message_size.sh", tmp_path, SEEDS="0")
    assert proc.returncode == 0, proc.stderr
    systems = sorted({_arg(c, "system") for c in calls if c[0] == "train"})
    assert systems == ["kuramoto10_ba", "quad3", "quad6"]
    (report,) = [c for c in calls if c[0] == "report"]
    assert _arg(report, "runs").count(",") == 2  # kuramoto, quad, quad_l2s


@pytest.mark.parametrize(
    ("env", "mpnode", "l2s"),
    [({"PAPER": "1"}, 4000, 10000), ({}, 40, 40), ({"PAPER": "1", "L2S_EPOCHS": "7"}, 4000, 7)],
)
def test_message_size_trains_l2s_for_its_own_budget(tmp_path, env, mpnode, l2s):
    # MPNODE.jl trains L2S for 10000 epochs and MP-NODE for 4000 (mpnode_reference.md), as table1.sh and table2.sh do
    proc, calls = run_recipe("message_size.sh", tmp_path, SEEDS="0", PARTS="quad", **env)
    assert proc.returncode == 0, proc.stderr
    epochs = {
        ("l2s" if "model=l2s" in c else "mpnode", int(_arg(c, "trainer.max_epochs"))) for c in calls if c[0] == "train"
    }
    assert epochs == {("mpnode", mpnode), ("l2s", l2s)}
    assert sum(c[0] == "train" for c in calls) == 8  # 3 and 6 quadrotors: m = 7, 13, 20 and L2S each


@pytest.mark.parametrize(
    ("env", "sizes"),
    [
        ({"PAPER": "1"}, {"quad3": 700, "quad6": 500}),
        ({}, {"quad3": 100, "quad6": 100}),
        ({"PAPER": "1", "Q6_N": "300"}, {"quad3": 700, "quad6": 300}),
    ],
)
def test_message_size_trains_six_quadrotors_on_table2s_target_size(tmp_path, env, sizes):
    # at PAPER=1 Figure 7's 6-quadrotor m = 13 and L2S runs are then table2.sh's scratch and L2S runs (one setting each)
    proc, calls = run_recipe("message_size.sh", tmp_path, SEEDS="0", PARTS="quad", **env)
    assert proc.returncode == 0, proc.stderr
    trains = [c for c in calls if c[0] == "train"]
    assert {(_arg(c, "system"), int(_arg(c, "data.n_train"))) for c in trains} == set(sizes.items())
    assert all(sum(a.startswith("data.n_train=") for a in c) == 1 for c in trains)  # one value, no Hydra clash


@pytest.mark.parametrize(
    ("recipe", "option", "value"),
    [
        ("message_size.sh", "Q6_N", "5OO"),
        ("message_size.sh", "L2S_EPOCHS", "1e4"),
        ("message_size.sh", "Q_EPOCHS", "0"),
        ("table2.sh", "DS", "50,l00"),
        ("table2.sh", "L2S_EPOCHS", "-1"),
        ("table1.sh", "N_TRAIN", "seven"),
    ],
)
def test_a_size_that_is_not_a_positive_integer_stops_the_recipe_before_anything_trains(tmp_path, recipe, option, value):
    # cli/lib.sh's check_counts: a typo in a size must not surface hours into a sweep
    proc, calls = run_recipe(recipe, tmp_path, SEEDS="0", PAPER="1", **{option: value})
    assert proc.returncode == 2
    assert f"{recipe}: {option}='{value}' is not a positive integer" in proc.stderr
    assert calls == []


@pytest.mark.parametrize("option", ["PARTS", "COLS"])  # COLS: table2.sh's older name for PARTS
def test_table2_parts_runs_only_the_columns_named(tmp_path, option):
    proc, calls = run_recipe("table2.sh", tmp_path, SEEDS="0", DS="50", **{option: "kuramoto"})
    assert proc.returncode == 0, proc.stderr
    trains = sorted(
        (_arg(c, "system"), _arg(c, "init") if any(a.startswith("init=") for a in c) else "-")
        for c in calls
        if c[0] == "train"
    )
    assert trains == [("kuramoto10_ba", "-"), ("kuramoto10_er", "kuramoto10_ba.ckpt"), ("kuramoto10_er", "null")]


@pytest.mark.slow  # long; outside the default suite (<4 min on 2 cores), run by .ci/run's -m slow step
def test_table2_starts_l2s_on_the_core_the_first_finished_mpnode_run_frees(tmp_path):
    """A column's finetune, scratch and L2S runs share one pool: L2S does not wait for the slowest MP-NODE run."""
    slow = "init=gene_ba_small.ckpt"  # the finetune
    proc, calls = run_recipe("table2.sh", tmp_path, PARTS="gene", SEEDS="0", JOBS="2", STUB_SLOW=slow)
    assert proc.returncode == 0, proc.stderr
    order = [
        ("finished" if c[0] == "finished" else _arg(c, "model") if "model=l2s" in c else _arg(c, "init"))
        for c in calls
        if c[0] in ("train", "finished") and _arg(c, "system") == "gene_ba_large"
    ]
    assert sorted(order) == sorted(["gene_ba_small.ckpt", "null", "l2s", "finished"])
    assert order.index("l2s") < order.index("finished")  # L2S began while the finetune was still training


@pytest.mark.parametrize(
    ("recipe", "parts", "bad"),
    [
        ("table2.sh", "lorenz kuramotoo", "kuramotoo"),
        ("table2.sh", "lorenz,kuramotoo", "kuramotoo"),
        ("foundation.sh", "pendulum pendulums", "pendulums"),
        ("message_size.sh", "kuramoto quads", "quads"),
    ],
)
def test_a_misspelt_part_stops_the_recipe_before_anything_trains(tmp_path, recipe, parts, bad):
    # the parts before the typo are valid: they must not train for hours and then fail on the typo
    proc, calls = run_recipe(recipe, tmp_path, SEEDS="0", PARTS=parts)
    assert proc.returncode == 2, proc.stderr
    assert f"{recipe}: unknown value '{bad}' in PARTS" in proc.stderr
    assert calls == []


def test_foundation_parts_pendulum_trains_messages_on_and_off(tmp_path):
    proc, calls = run_recipe("foundation.sh", tmp_path, SEEDS="0", PARTS="pendulum")
    assert proc.returncode == 0, proc.stderr
    trains = sorted((_arg(c, "system"), _arg(c, "model.zero_messages")) for c in calls if c[0] == "train")
    assert trains == [("pendulum2", "false"), ("pendulum2", "true")]
    layouts = [next((a for a in c if a.startswith("layout=")), None) for c in calls if c[0] == "report"]
    assert layouts == [None, "layout=messages"]  # the table, then Figure 3a
    assert (tmp_path / "foundation.sh" / "figure3a.md").is_file() and (
        tmp_path / "foundation.sh" / "figure3a.png"
    ).is_file()


def _figure3b_inputs(out, zeroed_toward):
    """A trained messages-on run and the four evaluations Figure 3b reads, with the zeroed model's prediction a
    tenth of the way from the uncoupled truth towards `zeroed_toward` ("coupled" or "uncoupled" itself)."""
    t = np.linspace(0, 1, 31)[None, :, None, None]  # [1, T, 1, 1]
    coupled = np.ones((3, 31, 2, 2)) + t  # [B, T, N, D]
    uncoupled = coupled + 2 * t  # the same initial states, parting over time
    zeroed = coupled if zeroed_toward == "coupled" else uncoupled + 0.1 * (coupled - uncoupled)
    (out / "pendulum2/s0-zero_messages_false/checkpoints").mkdir(parents=True)
    (out / "pendulum2/s0-zero_messages_false/checkpoints/best.ckpt").touch()
    for truth, x in (("coupled", coupled), ("uncoupled", uncoupled)):
        for zero, pred in (("false", coupled), ("true", zeroed)):
            d = out / "figure3b/s0" / f"{truth}_zero_messages_{zero}"
            d.mkdir(parents=True)
            np.savez(d / "test.npz", x=x)
            np.savez(d / "test_model.npz", x=pred)


@pytest.mark.parametrize(
    ("zeroed_toward", "verdict"),
    [
        ("uncoupled", "the nodes behave like uncoupled pendulums"),
        ("coupled", "the nodes do NOT behave like uncoupled pendulums"),
    ],
)
def test_foundation_figure3b_says_whether_zeroed_messages_leave_uncoupled_pendulums(tmp_path, zeroed_toward, verdict):
    _figure3b_inputs(tmp_path / "foundation.sh", zeroed_toward)
    proc, calls = run_recipe("foundation.sh", tmp_path, SEEDS="0", PARTS="pendulum")
    assert proc.returncode == 0, proc.stderr
    assert "RuntimeWarning" not in proc.stderr  # step 0, where both truths coincide, is not divided by zero
    assert not [c for c in calls if c[0] == "eval"]  # the evaluations that exist are kept
    text = (tmp_path / "foundation.sh" / "figure3b.md").read_text()
    assert f"With messages zeroed {verdict}" in text
    if zeroed_toward == "uncoupled":
        assert "| messages zeroed vs uncoupled, as a share of the two truths apart | 0.10 | 0.10 | 0.10 |" in text


def test_foundation_figure3b_evaluates_each_trained_coupled_model_four_ways(tmp_path):
    (tmp_path / "foundation.sh/pendulum2/s0-zero_messages_false/checkpoints").mkdir(parents=True)
    (tmp_path / "foundation.sh/pendulum2/s0-zero_messages_false/checkpoints/best.ckpt").touch()
    proc, calls = run_recipe("foundation.sh", tmp_path, SEEDS="0", PARTS="pendulum")
    evals = sorted((_arg(c, "model.zero_messages"), "system.spring=0" in c) for c in calls if c[0] == "eval")
    assert evals == [("false", False), ("false", True), ("true", False), ("true", True)]
    assert all(
        _arg(c, "init").endswith("s0-zero_messages_false/checkpoints/best.ckpt") for c in calls if c[0] == "eval"
    )


def test_diagnose_cases_refuses_an_unknown_case_before_simulating_anything(tmp_path):
    proc, calls = run_recipe("diagnose_cases.sh", tmp_path, CASES="a_damped b_vdpp")
    assert proc.returncode == 2, proc.stderr
    assert "diagnose_cases.sh: unknown value 'b_vdpp' in CASES" in proc.stderr and calls == []


@pytest.mark.slow  # long; outside the default suite (<4 min on 2 cores), run by .ci/run's -m slow step
@pytest.mark.parametrize("jobs", [1, 3])
def test_diagnose_cases_runs_jobs_at_once_each_run_in_its_own_checkpoint_folder(tmp_path, jobs):
    env = dict(CASES="a_damped case1 clean", SEEDS="0 1", NOISES="0", JOBS=str(jobs))
    proc, calls = run_recipe("diagnose_cases.sh", tmp_path, STUB_SLOW="fix=true", STUB_SLOW_S="2", **env)
    assert proc.returncode == 0, proc.stderr
    runs = {}  # checkpoint folder -> the commands that used it
    for c in calls:
        if c[0] in ("train", "diagnose"):
            runs.setdefault(_arg(c, "paths.ckpt_dir"), []).append(c[0])
    out = tmp_path / "diagnose_cases.sh"
    assert sorted(runs) == sorted(
        str(out / r / "checkpoints") for r in ("a_damped", "case1", "clean/noise0/seed0", "clean/noise0/seed1")
    )
    assert all(sorted(v) == ["diagnose", "train"] for v in runs.values())
    # how many diagnoses had begun when the first one finished: all at once up to JOBS, one by one with JOBS=1
    first_done = next(i for i, c in enumerate(calls) if c[0] == "finished")
    assert sum(c[0] == "diagnose" for c in calls[:first_done]) == min(jobs, 4)


def test_diagnose_cases_refuses_jobs_zero(tmp_path):
    proc, calls = run_recipe("diagnose_cases.sh", tmp_path, CASES="case1", JOBS="0")
    assert proc.returncode == 2 and "JOBS" in proc.stderr and calls == []


@pytest.mark.parametrize("seeds", ["0,1", "0 1"])  # lists take commas or spaces in every recipe
def test_table1_seeds_take_commas_or_spaces(tmp_path, seeds):
    proc, calls = run_recipe("table1.sh", tmp_path, SEEDS=seeds, MODELS="mpnode")
    assert proc.returncode == 0, proc.stderr
    assert sorted(_arg(c, "seed") for c in calls if c[0] == "train" and "-m" not in c) == ["0", "1"]


def test_table1_zero_shots_every_trained_model_not_only_the_ones_named(tmp_path):
    # a first call trains MP-NODE seeds 0 and 1; a second finishes L2S seed 0 alone: its table must still hold all three
    run_recipe("table1.sh", tmp_path, SEEDS="0,1", MODELS="mpnode")
    proc, calls = run_recipe("table1.sh", tmp_path, SEEDS="0", MODELS="l2s")
    assert proc.returncode == 0, proc.stderr
    assert [(_arg(c, "model"), _arg(c, "seed")) for c in calls if c[0] == "train" and "-m" not in c] == [("l2s", "0")]
    out = tmp_path / "table1.sh"
    zeroshot = sorted(_arg(c, "init") for c in calls if "mode=zeroshot" in c)
    assert zeroshot == [
        str(out / "checkpoints" / m / s / "gene_ba_small.ckpt")
        for m, s in [("l2s", "s0"), ("mpnode", "s0"), ("mpnode", "s1")]
    ]
    assert {_arg(c, "hydra.sweep.dir") for c in calls if "mode=zeroshot" in c} == {
        str(out / "zeroshot" / m / s) for m, s in [("l2s", "s0"), ("mpnode", "s0"), ("mpnode", "s1")]
    }


@pytest.mark.slow  # nine real `mpsim simulate` runs, about a minute
def test_meanfield_gene_simulates_the_mean_field_from_the_truths_states(tmp_path):
    script = Path(__file__).resolve().parents[1] / "cli" / "meanfield_gene.sh"
    env = {**os.environ, "OUT": str(tmp_path / "mf"), "N": "3", "CKPTS": ""}
    proc = subprocess.run(["bash", str(script)], env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    rows = {
        line.split(" | ")[0].lstrip("| "): line.split(" | ")[1:4]
        for line in (tmp_path / "mf" / "meanfield_gene.md").read_text().splitlines()
        if line.startswith("| closed-form")
    }
    k8, own = (
        rows["closed-form mean field, k̄ = 8 (BA's, what a BA-trained model can know)"],
        rows["closed-form mean field, each graph's own k̄"],
    )
    # BA(16, 8) and WS(16, 8) have mean degree 8 exactly, so both mean fields agree there; ER's k̄ is its own
    assert k8[0] == own[0] and k8[2] == own[2] and k8[1] != own[1]
    assert float(k8[0]) > 0.05  # BA's hubs: the mean field is far from the truth


@pytest.mark.parametrize("compare", ["table1=missing.ckpt", "no_equals_sign"])
def test_pernode_l2s_refuses_a_bad_compare_entry_before_anything_runs(tmp_path, compare):
    proc, calls = run_recipe("pernode_l2s.sh", tmp_path, COMPARE=compare)
    assert proc.returncode == 2 and calls == []
    assert f"COMPARE entry '{compare}' is not name=<an existing checkpoint>" in proc.stderr


def test_pernode_l2s_reads_each_seed_folder_not_the_runs_lock_files(tmp_path):
    out = tmp_path / "pernode_l2s.sh"
    (out / "data").mkdir(parents=True)
    x = np.arange(2 * 3 * 4, dtype=float).reshape(2, 3, 4, 1) + 1.0  # [B, T, N, D]
    for name in ("per_feature", "per_node"):
        np.savez(out / "data" / f"{name}.npz", x=x)
    run = out / "compare" / "other" / "per_feature"
    (run / "s0" / "eval").mkdir(parents=True)
    np.savez(run / "s0" / "eval" / "test.npz", x=x)
    np.savez(run / "s0" / "eval" / "test_model.npz", x=x + 0.5)
    (run / "s0.lock").touch()  # train_once leaves one beside every run
    ckpt = tmp_path / "other.ckpt"
    ckpt.touch()
    proc, calls = run_recipe("pernode_l2s.sh", tmp_path, RUNS="", COMPARE=f"other={ckpt}")
    assert proc.returncode == 0, proc.stderr
    assert calls == []  # nothing to train, and the evaluation is already there
    assert "| other | per_feature | 1 |" in (out / "pernode_l2s.md").read_text()


def test_pernode_l2s_simulates_the_system_and_draw_it_is_given(tmp_path):
    out = tmp_path / "pernode_l2s.sh"
    (out / "data" / "sim").mkdir(parents=True)
    x = np.arange(2 * 3 * 4, dtype=float).reshape(2, 3, 4, 1) + 1.0  # [B, T, N, D]
    np.savez(out / "data" / "sim" / "trajectories.npz", x=x)  # what the stub's simulate would have written
    proc, calls = run_recipe("pernode_l2s.sh", tmp_path, RUNS="", SYSTEM="gene_ba_large", DATA_SEED="7")
    assert proc.returncode == 0, proc.stderr
    (sim,) = calls
    assert sim[0] == "simulate" and _arg(sim, "system") == "gene_ba_large" and _arg(sim, "data.seed") == "7"
    with np.load(out / "data" / "per_node.npz") as z:
        per_node = z["x"]  # [B, T, N, D] z-scored node by node
    np.testing.assert_allclose(per_node.mean(axis=(0, 1)), 0.0, atol=1e-12)
    np.testing.assert_allclose(per_node.std(axis=(0, 1)), 1.0)
    assert (out / "pernode_l2s.md").read_text().startswith("# gene_ba_large (data.seed 7) trained")
    assert (out / "data" / "draw.txt").read_text() == "system=gene_ba_large data.seed=7\n"  # what a resume checks


@pytest.mark.parametrize(("option", "value"), [("SYSTEM", "lorenz10"), ("DATA_SEED", "-1")])
def test_pernode_l2s_refuses_a_bad_system_or_draw_before_anything_runs(tmp_path, option, value):
    proc, calls = run_recipe("pernode_l2s.sh", tmp_path, **{option: value})
    assert proc.returncode == 2 and calls == []
    assert f"{option}='{value}'" in proc.stderr


@pytest.mark.parametrize("held", ["system=gene_ba_large data.seed=7", None])  # None: data kept before draw.txt
def test_pernode_l2s_refuses_kept_data_of_another_draw(tmp_path, held):
    data = tmp_path / "pernode_l2s.sh" / "data"
    data.mkdir(parents=True)
    np.savez(data / "per_node.npz", x=np.zeros((1, 2, 3, 1)))
    if held is not None:
        (data / "draw.txt").write_text(held + "\n")
    proc, calls = run_recipe("pernode_l2s.sh", tmp_path, SYSTEM="gene_ba_large", DATA_SEED="3")
    assert proc.returncode == 2 and calls == []
    expected = held or "system=gene_ba_small data.seed=0"
    assert f"holds the draw '{expected}', not 'system=gene_ba_large data.seed=3'" in proc.stderr
