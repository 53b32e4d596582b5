"""`mpsim.resume`: the run that `resume=` continues, found before Hydra starts (end to end in tests/test_cli.py and
the fault matrix)."""

from __future__ import annotations

from pathlib import Path

import yaml

from mpsim.resume import find_resumable


def test_resume_true_passes_over_a_run_whose_record_is_damaged(tmp_path):
    """`resume=true` searches every earlier run's overrides.yaml: a damaged one matches nothing (and is not an
    error there), so the newest intact run with the same overrides is found."""

    def run(name: str, record: str) -> Path:
        d = tmp_path / "outputs" / "train" / "2026-11-29" / name
        (d / ".hydra").mkdir(parents=True)
        (d / ".hydra" / "overrides.yaml").write_text(record)
        (d / "checkpoints").mkdir()
        (d / "checkpoints" / "last.ckpt").write_bytes(b"")
        return d

    args = ["system=lorenz3", "seed=2", f"paths.output_root={tmp_path / 'outputs'}"]
    intact = run("a", yaml.safe_dump(args))
    run("b", "!!python/object/apply:os.system ['touch pwned.txt']\n")
    run("c", "{seed: 2}\n")
    assert find_resumable([*args, "resume=true", "trainer.max_epochs=9"]) == intact
    assert find_resumable(["system=lorenz3", "seed=3", f"paths.output_root={tmp_path / 'outputs'}"]) is None
    assert not (tmp_path / "pwned.txt").exists()
