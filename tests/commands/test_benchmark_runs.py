"""`mpsim train` in-process on the MP-NODE benchmark systems: baselines, transfer across graph sizes, controls."""

import math

import pytest

from mpsim.commands.train import run_train
from mpsim.errors import IncompatibleError

TINY = [
    "trainer=quick",
    "trainer.max_epochs=1",
    "trainer.progress=false",
    "data.n_train=4",
    "data.n_val=2",
    "data.n_test=2",
    "data.horizon=5",
    "eval.horizons=[1,5]",
    "eval.plots=false",
]


def _train(cfg_factory, tmp_path, name, *overrides):
    overrides = [*TINY, *overrides]
    return run_train(cfg_factory("train", *overrides), output_dir=tmp_path / name, overrides=overrides)


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_node_trains_then_refuses_another_graph_size(cfg_factory, tmp_path):
    summary = _train(cfg_factory, tmp_path, "node", "system=gene_ba_small", "model=node")
    assert summary["model"]["model"] == "NODE" and summary["model"]["n_nodes"] == 16
    ckpt = str(tmp_path / "checkpoints" / "gene_ba_small.ckpt")
    for mode in ("finetune", "zeroshot"):  # 16 → 64 nodes: refused with the reason and the way out
        with pytest.raises(IncompatibleError, match="flattened state of 16 nodes.*64 nodes.*model=mpnode"):
            _train(cfg_factory, tmp_path, f"bad_{mode}", "system=gene_ba_large", f"mode={mode}", f"init={ckpt}")
        assert not (tmp_path / f"bad_{mode}" / "summary.json").exists()
    # same node count, another graph family: a NODE ignores the graph, so zero-shot runs
    zero = _train(cfg_factory, tmp_path, "node_er", "system=gene_er_small", "mode=zeroshot", f"init={ckpt}")
    assert zero["mode"] == "zeroshot" and math.isfinite(zero["test"]["rmse"])


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_mpnode_on_quadrotors_finetunes_from_three_to_six(cfg_factory, tmp_path):
    # the Table 2 quadrotor column's path: controls (4 rotor thrusts per node), then a larger swarm
    pre = _train(cfg_factory, tmp_path, "quad3", "system=quad3", "solver=rk4", "model.message_size=7")
    assert pre["model"]["n_params"] > 0 and pre["system"]["n_nodes"] == 3
    ckpt = str(tmp_path / "checkpoints" / "quad3.ckpt")
    fine = _train(
        cfg_factory, tmp_path, "quad6", "system=quad6", "solver=rk4", f"init={ckpt}", "mode.refit_normalisation=true"
    )
    assert fine["mode"] == "finetune" and fine["system"]["n_nodes"] == 6
    assert fine["model"]["config"]["message_size"] == 7  # the architecture comes from the checkpoint
    assert math.isfinite(fine["initial_test_error"]) and math.isfinite(fine["min_test_error"])


def test_l2s_finetunes_across_graph_sizes(cfg_factory, tmp_path):
    # sum aggregation has no weight tied to N: an L2S checkpoint of 16 nodes runs on 64
    _train(cfg_factory, tmp_path, "l2s", "system=gene_ba_small", "model=l2s")
    ckpt = str(tmp_path / "checkpoints" / "gene_ba_small.ckpt")
    zero = _train(cfg_factory, tmp_path, "l2s_large", "system=gene_ba_large", "mode=zeroshot", f"init={ckpt}")
    assert zero["model"]["model"] == "L2S" and math.isfinite(zero["test"]["rmse"])
