import pytest
import torch

from mpsim.errors import CheckpointError
from mpsim.models import MPNODE
from mpsim.training.checkpoint import load_checkpoint, save_checkpoint


def _payload(model):
    return {
        "model": {"config": {"_target_": "mpsim.models.MPNODE", "hidden": 32}, "state_dim": 2, "control_dim": 0,
                  "state_dict": model.state_dict()},
        "normalisation": {"mean": torch.zeros(2), "std": torch.ones(2)},
        "system": {"system": "pendulum2", "state_names": ["theta", "omega"], "params": {"g": 9.81}},
        "trainer": {"optimizer": torch.optim.Adam(model.parameters()).state_dict(), "rng": torch.get_rng_state()},
    }


def test_round_trip_with_weights_only(tmp_path):
    model = MPNODE(2)
    path = save_checkpoint(tmp_path / "a.ckpt", _payload(model))
    back = load_checkpoint(path)  # torch.load(weights_only=True) inside
    other = MPNODE(2)
    other.load_state_dict(back["model"]["state_dict"])
    for a, b in zip(model.parameters(), other.parameters(), strict=True):
        assert torch.equal(a, b)
    assert back["system"]["params"]["g"] == 9.81
    assert [p.name for p in tmp_path.iterdir()] == ["a.ckpt"]  # no temporary file left behind


def test_truncated_file_is_a_clear_error(tmp_path):
    path = save_checkpoint(tmp_path / "a.ckpt", _payload(MPNODE(2)))
    path.write_bytes(path.read_bytes()[:200])
    with pytest.raises(CheckpointError, match="cannot read checkpoint .* truncated"):
        load_checkpoint(path)


def test_foreign_and_newer_files_are_refused(tmp_path):
    torch.save({"weights": torch.zeros(1)}, tmp_path / "foreign.pt")
    with pytest.raises(CheckpointError, match="not an mpsim checkpoint"):
        load_checkpoint(tmp_path / "foreign.pt")
    path = save_checkpoint(tmp_path / "new.ckpt", {**_payload(MPNODE(2)), "version": 99})
    with pytest.raises(CheckpointError, match="newer mpsim"):
        load_checkpoint(path)
    with pytest.raises(CheckpointError, match="does not exist"):
        load_checkpoint(tmp_path / "missing.ckpt")


def test_pickled_objects_are_not_loaded(tmp_path):
    # weights_only=True refuses arbitrary Python objects instead of executing them
    torch.save({"format": "mpsim-checkpoint", "version": 1, "evil": object()}, tmp_path / "x.ckpt")
    with pytest.raises(CheckpointError):
        load_checkpoint(tmp_path / "x.ckpt")
