import json
import re

import pytest
import torch

from mpsim.commands.init_ckpt import check_checkpoint_system, check_weights_fit, resolve_init
from mpsim.commands.runtime import Runtime
from mpsim.errors import CheckpointError, IncompatibleError
from mpsim.training.checkpoint import capped_meta

QUAD = ["px", "py", "pz", "qw", "qx", "qy", "qz", "vx", "vy", "vz", "wx", "wy", "wz"]


def _ckpt(state_dim, control_dim, names):
    return {
        "path": "m.ckpt",
        "system": {"system": "quad3", "state_names": names},
        "model": {"state_dim": state_dim, "control_dim": control_dim},
    }


@pytest.mark.parametrize(
    ("trained", "data", "fix"),
    [
        ((13, 4, QUAD), (13, 0, QUAD), r"Give the data the 4 control inputs per node .*`u` \[B, T, N, 4\]"),
        ((13, 4, QUAD), (13, 2, QUAD), r"Give the data the 4 control inputs per node"),
        ((2, 0, ["theta", "omega"]), (2, 3, ["theta", "omega"]), r"This model takes no control inputs: drop `u`"),
        ((13, 4, QUAD), (2, 0, ["theta", "omega"]), r"Use a checkpoint of a system with the same node state"),
    ],
)
def test_a_model_and_data_that_differ_say_which_side_to_change(trained, data, fix):
    # same node state, other inputs: the data lack (or carry extra) controls, not the checkpoint's system
    with pytest.raises(IncompatibleError, match=rf"was trained on quad3 .* but this data has .*{fix}"):
        check_checkpoint_system(_ckpt(*trained), data[0], data[1], data[2])
    check_checkpoint_system(_ckpt(*trained), *trained)  # matching data pass


def test_a_run_directory_given_as_init_is_refused_naming_its_model_file(tmp_path):
    """init=<run dir> is a common slip: the message names the run's best.ckpt (and a plain folder just as a folder)."""
    rt = Runtime(torch.device("cpu"), torch.float32, tmp_path, tmp_path / "out", [])
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "best.ckpt").write_bytes(b"x")
    with pytest.raises(
        CheckpointError,
        match=re.escape(
            f"is a folder, not a checkpoint file; a run's model is its checkpoints/best.ckpt: init={run}/checkpoints/best.ckpt"
        ),
    ):
        resolve_init("run", rt, "checkpoints")
    (tmp_path / "empty").mkdir()
    with pytest.raises(CheckpointError, match=r"empty is a folder, not a checkpoint file\.$"):
        resolve_init("empty", rt, "checkpoints")
    with pytest.raises(CheckpointError, match=r"no such checkpoint \(looked for [^,]*/gone, [^,]*/checkpoints/gone, "):
        resolve_init("gone", rt, "checkpoints")
    assert resolve_init(f"{run}/checkpoints/best.ckpt", rt, "checkpoints") == run / "checkpoints" / "best.ckpt"


def _with_weights(state: dict, config: dict) -> dict:
    return {"path": "m.ckpt", "model": {"config": config, "state_dict": state}}


def test_weights_that_do_not_fit_name_the_override_or_else_the_tensor_and_both_shapes():
    own = {"net.0.weight": torch.empty(12000, 6, device="meta"), "effects.0.coef": torch.empty(1, device="meta")}
    saved = {"net.0.weight": torch.zeros(32, 6)}
    config = {"_target_": "mpsim.models.mpnode.MPNODE", "hidden": 12000}
    with pytest.raises(CheckpointError, match=r"m.ckpt does not fit this model \(model.hidden: checkpoint 32, config"):
        check_weights_fit(own, _with_weights(saved, {**config, "hidden": 32}), config)
    with pytest.raises(
        CheckpointError,
        match=re.escape(
            "m.ckpt: its model.config does not describe its weights: model.state_dict['net.0.weight'] is [32, 6] "
            "but the config builds [12000, 6] (1 tensor(s) differ)."
        ),
    ):
        check_weights_fit(own, _with_weights(saved, config), config)
    with pytest.raises(
        CheckpointError, match=r"model.state_dict lacks 'net.1.bias' \(\[7\]\), which the config builds"
    ):
        check_weights_fit({"net.1.bias": torch.empty(7, device="meta")}, _with_weights(saved, config), config)
    # effects added on top of a checkpoint start from their configured values; extra checkpoint tensors are unused
    check_weights_fit({"effects.0.coef": own["effects.0.coef"]}, _with_weights(saved, config), config)


def test_large_data_metadata_is_not_copied_into_checkpoints_and_the_warning_names_it(caplog):
    meta = {
        "system": "measured",
        "state_names": ["theta", "omega"],
        "n_nodes": 2,
        "notes": "x" * 100_000,
        "calibration": list(range(20_000)),
        "units": {"theta": "rad"},
        "seed": 3,
    }
    with caplog.at_level("WARNING"):
        kept = capped_meta(meta, "the checkpoints")
    assert kept == {
        "system": "measured",
        "state_names": ["theta", "omega"],
        "n_nodes": 2,
        "units": {"theta": "rad"},
        "seed": 3,
    }
    assert list(kept) == [k for k in meta if k in kept]  # in the data's order
    (warning,) = [r.getMessage() for r in caplog.records]
    assert "not copied into the checkpoints (at most 64 kB" in warning and warning.endswith(
        "notes (100 kB), calibration (129 kB)"
    )
    # the keys read back come first: with room for them only, every other key is left out
    room = sum(len(json.dumps({k: meta[k]})) for k in ("system", "state_names", "n_nodes"))
    assert list(capped_meta(meta, "x", budget=room)) == ["system", "state_names", "n_nodes"]
    caplog.clear()
    small = {"system": "lorenz3", "dt": 0.05, "params": {"rho": 28.0, "H": [[0.0, 0.1], [0.2, 0.0]]}}
    assert capped_meta(small, "x") == small and not caplog.records
