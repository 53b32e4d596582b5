"""`bench=epoch_time`: real training runs, their per-epoch times and the projected paper budget."""

import shutil
from pathlib import Path

import pytest
import torch

from mpsim.bench.epoch_time import PAPER_CASES, EpochTimeBench
from mpsim.errors import ConfigError
from tests.helpers import run_recipe


@pytest.mark.slow  # long; outside the default suite (<4 min on 2 cores), run by .ci/run's -m slow step
def test_epoch_time_rows_come_from_a_real_training_run():
    bench = EpochTimeBench(
        cases=[
            {
                "name": "tiny",
                "overrides": ["system=pendulum2", "data.n_train=8", "data.horizon=10"],
                "paper_epochs": 4000,
            }
        ],
        epochs=3,
    )
    (row,) = bench.run()
    # epoch 0 (evaluation) and the warm-up dropped
    assert row["case"] == "tiny" and row["device"] == "cpu" and row["epochs_timed"] == 2
    assert row["source"] == "this checkout"
    assert 0 < row["train_pass_s"] <= row["epoch_with_eval_s"]
    assert row["paper_budget_h"] == pytest.approx(4000 * row["epoch_with_eval_s"] / 3600, abs=0.006)
    assert f"{row['paper_budget_h']:.1f} h" in bench.summarise([row])[0]


def test_epoch_time_refuses_bad_cases_and_keeps_paper_defaults():
    with pytest.raises(ConfigError, match="name and a list of overrides"):
        EpochTimeBench(cases=[{"name": "x", "overrides": "system=lorenz3"}])
    with pytest.raises(ConfigError, match="epochs must be >= 2"):
        EpochTimeBench(epochs=1)
    assert {c["paper_epochs"] for c in PAPER_CASES} == {4000, 10000}  # MP-NODE 4000, L2S 10000 (the paper's)
    with pytest.raises(ConfigError, match="matches no case; the cases are: 'gene 4×4 BA"):
        EpochTimeBench(only=["no such case"])
    quads = EpochTimeBench(only=["quadrotors"]).cases
    assert len(quads) == 3 and all("quadrotors" in c["name"] for c in quads)
    assert len(EpochTimeBench(only="8×8").cases) == 2  # a single string from the command line
    assert len(EpochTimeBench(only=["8x8"]).cases) == 2  # `×` cannot be typed unquoted on Hydra's command line


def test_every_child_trains_on_the_bench_device(monkeypatch):
    """`mpsim train` picks `device=auto`: without `device=` passed on, a CPU bench on a GPU machine timed the GPU."""
    seen = []

    def fake_run(cmd, **kwargs):
        seen.append(cmd)
        raise RuntimeError("stop here")

    monkeypatch.setattr("mpsim.bench.epoch_time.subprocess.run", fake_run)
    for device in ("cpu", "auto"):
        with pytest.raises(RuntimeError, match="stop here"):
            EpochTimeBench(only=["pendulum"], device=device).run()
    want = "device=cuda" if torch.cuda.is_available() else "device=cpu"
    assert "device=cpu" in seen[0] and want in seen[1]
    assert EpochTimeBench(only=["pendulum"]).device == "cpu"
    with pytest.raises(ConfigError, match="device=tpu is not supported"):
        EpochTimeBench(device="tpu")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="CUDA is not available"):
            EpochTimeBench(device="cuda")


def test_a_failing_case_names_its_command():
    bench = EpochTimeBench(cases=[{"name": "bad", "overrides": ["system=no_such_system"]}], epochs=2)
    with pytest.raises(RuntimeError, match="system=no_such_system"):
        bench.run()


def test_a_case_with_a_source_trains_with_that_checkouts_code(tmp_path):
    """`source` puts another checkout's mpsim first on the child's path (the code before a change, timed beside it)."""
    before = tmp_path / "before" / "src"
    (before / "mpsim").mkdir(parents=True)
    (before / "mpsim" / "__init__.py").write_text("")
    (before / "mpsim" / "__main__.py").write_text("raise SystemExit('the code before ran')\n")
    case = {"name": "tiny", "overrides": ["system=pendulum2", "data.n_train=8", "data.horizon=10"]}
    bench = EpochTimeBench(cases=[{**case, "source": str(before)}], epochs=2)
    assert bench.cases[0]["source"] == str(before.resolve())
    with pytest.raises(RuntimeError, match="the code before ran"):
        bench.run()
    with pytest.raises(ConfigError, match="src folder of an mpsim checkout"):
        EpochTimeBench(cases=[{**case, "source": str(tmp_path)}])


def test_trained_cases_pair_fresh_and_kept_checkpoints():
    """bench=epoch_time_trained: every trained case starts from a checkpoint kept in the repository and has a
    fresh-weights twin with the same overrides, so each pair is a side-by-side ratio."""
    import yaml

    root = Path(__file__).resolve().parents[2]
    cfg = yaml.safe_load((root / "src/mpsim/conf/bench/epoch_time_trained.yaml").read_text())
    cases = EpochTimeBench(cases=cfg["cases"]).cases
    fresh = {tuple(c["overrides"]) for c in cases if not any(o.startswith("init=") for o in c["overrides"])}
    trained = [c for c in cases if any(o.startswith("init=") for o in c["overrides"])]
    assert len(trained) == len(fresh) >= 3
    for c in trained:
        (init,) = [o.removeprefix("init=") for o in c["overrides"] if o.startswith("init=")]
        assert (root / init).is_file(), f"{c['name']}: {init} is not in the repository"
        assert tuple(o for o in c["overrides"] if not o.startswith("init=")) in fresh, c["name"]


@pytest.mark.parametrize("case", PAPER_CASES, ids=lambda c: c["name"])
def test_every_paper_case_composes_as_a_train_config(cfg_factory, case):
    """A typo in a paper case would otherwise surface only after minutes of data simulation."""
    cfg = cfg_factory("train", *case["overrides"], "trainer=paper")
    sizes = {o.split("=")[0]: int(o.split("=")[1]) for o in case["overrides"] if o.startswith("data.n_")}
    assert {k: cfg.data[k.removeprefix("data.")] for k in sizes} == sizes
    assert cfg.trainer.batch_size == 128


# --- the paper cases time what the PAPER=1 recipes train -------------------------------------------------------------
# Each recipe runs with a stub `mpsim` (tests.helpers.run_recipe), so the recipes' own PAPER=1 settings are read, not
# restated here.
_RECIPES = {  # recipe: the environment that keeps it to one seed
    "table1.sh": {"SEEDS": "0"},
    "table2.sh": {"SEEDS": "0"},
    "message_size.sh": {"SEEDS": "0"},
    "foundation.sh": {"SEEDS": "0", "PARTS": "pendulum"},
}
_DATA_KEYS = ("system=", "data.", "solver=")  # what sets the data a case trains on


@pytest.fixture(scope="module")
def paper_recipe_calls(tmp_path_factory):
    if shutil.which("flock") is None:
        pytest.skip("the recipes need flock (util-linux)")
    tmp = tmp_path_factory.mktemp("recipes")
    calls = []
    for recipe, extra in _RECIPES.items():
        proc, made = run_recipe(recipe, tmp, PAPER="1", **extra)
        assert proc.returncode == 0, f"{recipe} with a stub mpsim failed:\n{proc.stdout}\n{proc.stderr}"
        calls += [c[1:] for c in made if c[0] == "train" and "-m" not in c]
    return calls


@pytest.mark.parametrize("case", PAPER_CASES, ids=[c["name"] for c in PAPER_CASES])
def test_every_paper_case_times_a_run_a_paper_recipe_trains(paper_recipe_calls, case):
    """A case matches a recipe's PAPER=1 training call when the call has every override of the case and trains on the
    same data (no system=/data./solver= setting the case lacks) with the paper's trainer; a recipe that changes its
    PAPER=1 data (say, QH=60) leaves a case without a match, and this test names it."""
    wanted = set(case["overrides"])
    matches = [
        call
        for call in paper_recipe_calls
        if wanted <= set(call) and "trainer=paper" in call and {a for a in call if a.startswith(_DATA_KEYS)} <= wanted
    ]
    assert matches, f"no PAPER=1 recipe trains {case['name']!r} ({' '.join(case['overrides'])})"
