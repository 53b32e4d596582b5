import json
import math

import pytest
import torch

from mpsim.errors import CheckpointError
from mpsim.models import MPNODE
from mpsim.training.checkpoint import history_row, history_text, load_checkpoint, save_checkpoint


def _payload(model):
    return {
        "model": {
            "config": {"_target_": "mpsim.models.MPNODE", "hidden": 32},
            "state_dim": 2,
            "control_dim": 0,
            "state_dict": model.state_dict(),
        },
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


def test_checksum_detects_altered_content(tmp_path):
    path = save_checkpoint(tmp_path / "a.ckpt", _payload(MPNODE(2)))
    data = torch.load(path, weights_only=True)
    assert len(data["checksum"]) == 64
    first = next(iter(data["model"]["state_dict"]))
    data["model"]["state_dict"][first].view(-1)[0] += 1.0  # one weight changed, the stored checksum kept
    torch.save(data, path)
    with pytest.raises(CheckpointError, match="does not match the checksum"):
        load_checkpoint(path)


def test_non_finite_weights_are_refused(tmp_path):
    payload = _payload(MPNODE(2))
    first = next(iter(payload["model"]["state_dict"]))
    payload["model"]["state_dict"][first].view(-1)[0] = float("inf")
    path = save_checkpoint(tmp_path / "a.ckpt", payload)
    with pytest.raises(CheckpointError, match=rf"state_dict\['{first}'\] holds NaN/inf \(1 of"):
        load_checkpoint(path)


def test_incomplete_checkpoints_name_the_missing_key(tmp_path):
    payload = _payload(MPNODE(2))
    del payload["model"]["state_dim"]
    path = save_checkpoint(tmp_path / "a.ckpt", payload)
    with pytest.raises(CheckpointError, match="lacks 'model.state_dim'"):
        load_checkpoint(path)
    (tmp_path / "empty.ckpt").write_bytes(b"")
    with pytest.raises(CheckpointError, match=r"is empty \(0 bytes\)"):
        load_checkpoint(tmp_path / "empty.ckpt")


def test_targets_outside_mpsim_need_the_users_own_config(tmp_path):
    payload = _payload(MPNODE(2))
    payload["model"]["config"]["effects"] = [{"_target_": "collections.OrderedDict"}]
    path = save_checkpoint(tmp_path / "a.ckpt", payload)
    with pytest.raises(CheckpointError, match=r"model.effects\[0\]._target_='collections.OrderedDict' is not an mpsim"):
        load_checkpoint(path)
    assert load_checkpoint(path, allowed_targets={"collections.OrderedDict"})["model"]["config"]["effects"]


@pytest.mark.parametrize(
    "target, ok",
    [
        ("mpsim.models.mpnode.MPNODE", True),  # the configs' module paths
        ("mpsim.models.MPNODE", True),  # package paths, as in checkpoints written before: they still load
        ("mpsim.effects.LinearDamping", True),
        ("mpsim.files.atomic_write", False),
        ("mpsim.training.checkpoint.torch", False),
        ("mpsim..x", False),
        ("pathlib.Path", False),
        ("builtins.eval", False),
    ],
)
def test_only_mpsim_classes_are_allowed(target, ok):
    from mpsim.training.checkpoint import check_config_targets, is_mpsim_class

    assert is_mpsim_class(target) is ok
    if not ok:
        with pytest.raises(CheckpointError, match="is not an mpsim class"):
            check_config_targets({"_target_": "mpsim.models.MPNODE", "effects": [{"_target_": target}]}, "x")


def test_a_model_config_is_required_only_to_build_a_model(tmp_path):
    payload = _payload(MPNODE(2))
    del payload["model"]["config"]  # e.g. a Trainer used as a library, without a checkpoint base
    path = save_checkpoint(tmp_path / "a.ckpt", payload)
    assert load_checkpoint(path)["model"]["state_dim"] == 2
    with pytest.raises(CheckpointError, match="lacks 'model.config'"):
        load_checkpoint(path, need_config=True)


def _rows(n):
    return [{"epoch": i, "train_loss": math.nan if i == 0 else 1.0 / (i + 3), "lr": 1e-3} for i in range(n)]


def test_history_is_stored_as_text_and_read_back_as_rows(tmp_path):
    rows = _rows(50)
    payload = _payload(MPNODE(2))
    payload["trainer"]["history_json"] = history_text(list(rows[0]), [history_row(r, list(rows[0])) for r in rows])
    back = load_checkpoint(save_checkpoint(tmp_path / "a.ckpt", payload))["trainer"]
    assert "history_json" not in back and len(back["history"]) == 50
    assert back["history"][1:] == rows[1:] and math.isnan(back["history"][0]["train_loss"])
    assert type(back["history"][7]["epoch"]) is int  # epochs stay integers (metrics.csv prints them so)


def test_a_row_with_other_keys_is_stored_whole():
    assert json.loads(history_row({"epoch": 1, "extra": 2.5}, ["epoch"])) == {"epoch": 1, "extra": 2.5}
    assert json.loads(history_row({"epoch": 1}, ["epoch"])) == [1]


def test_older_checkpoints_with_a_list_of_rows_still_load(tmp_path):
    payload = _payload(MPNODE(2))
    payload["trainer"]["history"] = _rows(3)
    back = load_checkpoint(save_checkpoint(tmp_path / "a.ckpt", payload))["trainer"]
    assert back["history"][1:] == _rows(3)[1:]


@pytest.mark.parametrize(
    "text",
    [
        "not json",
        '{"columns": ["epoch"], "rows": [[1, 2]]}',
        '{"columns": ["epoch"]}',
        "[1, 2]",
        '{"columns": [1], "rows": [[1]]}',
        7,
    ],
)
def test_a_damaged_history_is_one_clear_error(tmp_path, text):
    payload = _payload(MPNODE(2))
    payload["trainer"]["history_json"] = text  # written with a valid checksum: damaged before it was saved
    path = save_checkpoint(tmp_path / "a.ckpt", payload)
    with pytest.raises(CheckpointError, match="history_json.*damaged.*without resume"):
        load_checkpoint(path)
