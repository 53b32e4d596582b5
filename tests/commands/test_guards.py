"""Memory guards before work starts (`mpsim.commands.guards`): the advice names what makes the job smaller."""

from __future__ import annotations

import pytest
import torch

from mpsim import memory
from mpsim.commands.guards import check_training_memory
from mpsim.commands.runtime import Runtime
from mpsim.data.trajectories import Trajectories
from mpsim.errors import ResourceError
from mpsim.models.equations import EquationsModel


def _data(segments: bool) -> Trajectories:
    meta = {
        "state_names": ["q", "v"],
        **({"segments": [{"recording": "r.csv", "index": 0, "t0": 0.0}]} if segments else {}),
    }
    return Trajectories(
        t=torch.arange(5.0), x=torch.zeros(1, 5, 1, 2), edge_index=torch.zeros(2, 0, dtype=torch.long), meta=meta
    )


@pytest.mark.parametrize("segments", [True, False])
def test_training_memory_advice_names_data_keys_for_recordings(tmp_path, monkeypatch, segments):
    monkeypatch.setattr(memory, "available_bytes", lambda device="cpu": 10)
    rt = Runtime(torch.device("cpu"), torch.float32, tmp_path, tmp_path, [])
    model = EquationsModel(2, spec={"states": ["q", "v"], "equations": {"q": "v", "v": "-k*q"}, "params": {"k": 1.0}})
    with pytest.raises(ResourceError) as err:
        check_training_memory(rt, model, {}, _data(segments), 8, None)
    assert ("data.segment=<shorter>; data.stride=<k>" in str(err.value)) == segments
    assert "trainer.batch_size" in str(err.value)
