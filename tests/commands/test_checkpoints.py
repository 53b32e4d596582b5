import re

import pytest
import torch

from mpsim.commands.checkpoints import check_checkpoint_system, resolve_init
from mpsim.commands.runtime import Runtime
from mpsim.errors import CheckpointError, IncompatibleError

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
