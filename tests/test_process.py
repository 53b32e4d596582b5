import pytest
import torch

from mpsim.errors import ConfigError
from mpsim.process import resolve_device


def test_auto_and_cpu_resolve_here():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")


@pytest.mark.parametrize(
    ("device", "cuda_count", "mps", "match"),
    [
        ("cuda", 0, False, "device=cuda but CUDA is not available on this machine; use device=cpu"),
        ("cuda:3", 1, False, r"device=cuda:3 but this machine has 1 CUDA device\(s\), cuda:0 to cuda:0"),
        ("mps", 0, False, "device=mps but Apple's MPS backend is not available"),  # was torch's traceback
        ("tpu", 0, False, "device=tpu is not supported; choose auto, cpu, cuda, cuda:<index> or mps"),
    ],
)
def test_a_device_this_machine_lacks_is_one_message(monkeypatch, device, cuda_count, mps, match):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: cuda_count > 0)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: cuda_count)
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: mps)
    with pytest.raises(ConfigError, match=match):
        resolve_device(device)


def test_a_device_this_machine_has_resolves(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert resolve_device("cuda:1") == torch.device("cuda:1")
    assert resolve_device("auto") == torch.device("cuda")
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: True)
    assert resolve_device("mps") == torch.device("mps")
