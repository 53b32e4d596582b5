"""mpsim.files: atomic writes survive Ctrl-C."""

import signal

import pytest
import torch

from mpsim.files import atomic_write


def test_ctrl_c_during_a_checkpoint_write_lands_after_the_file_is_whole(tmp_path):
    # SIGINT inside torch.save used to raise in its zip writer, whose clean-up then failed with a RuntimeError
    # that hid the interrupt (CI: `mpsim train` exited 1 with a traceback instead of 130 and the resume hint)
    payload = {"w": torch.arange(100_000, dtype=torch.float64)}
    steps: list[str] = []

    def write(f):
        f.write(b"")  # the file is open
        signal.raise_signal(signal.SIGINT)  # Ctrl-C in the middle of the write: torch.save still to come
        steps.append("after the signal")
        torch.save(payload, f)

    # Python's own Ctrl-C handler, whatever the test runner installed (the interrupt must reach *this* handler)
    runner = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            atomic_write(tmp_path / "last.ckpt", write)
        handler = signal.getsignal(signal.SIGINT)
    finally:
        signal.signal(signal.SIGINT, runner)
    assert steps == ["after the signal"]  # the write went on
    assert torch.equal(torch.load(tmp_path / "last.ckpt")["w"], payload["w"])  # and the file is whole
    assert handler is signal.default_int_handler  # the handler is back
    assert [p.name for p in tmp_path.iterdir()] == ["last.ckpt"]  # no temporary file left
