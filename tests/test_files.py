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


def test_temporary_files_name_their_process_and_only_orphans_are_removed(tmp_path, monkeypatch):
    import os
    import subprocess
    import sys
    import time

    import mpsim.files as files

    seen = []
    atomic_write(tmp_path / "a.txt", lambda f: seen.extend(p.name for p in tmp_path.iterdir()), mode="w")
    (name,) = seen
    assert files._TMP_NAME.match(name) and f".mpsim-{os.getpid()}-{files._HOST}." in name  # what the sweep reads
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    orphan = tmp_path / f".b.txt.mpsim-{gone.pid}-{files._HOST}.abcd_123.tmp"
    live = tmp_path / f".c.txt.mpsim-{os.getpid()}-{files._HOST}.abcd_123.tmp"
    for p in (orphan, live):
        p.write_text("half")
        os.utime(p, (time.time() - 3600,) * 2)
    assert files.remove_orphaned_temps(tmp_path) == []  # this folder was looked at already, by the write above
    monkeypatch.setattr(files, "_swept", set())
    assert files.remove_orphaned_temps(tmp_path) == [orphan]
    assert live.exists() and (tmp_path / "a.txt").is_file()
