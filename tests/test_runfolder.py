"""mpsim.runfolder: a failed command removes exactly what it made; a folder that holds a run is recognised and
backed up whole."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from mpsim.errors import OutputError
from mpsim.runfolder import RunFolder, holds_run, make_folders, move_to_backup


def _record(path: Path, created: list[Path], log: str = "train.log") -> RunFolder:
    """What `prepare` keeps for `path` before Hydra writes there."""
    before = (path / log).stat() if (path / log).is_file() else None
    return RunFolder(
        path=path,
        created=created,
        kept=set(os.listdir(path)),
        record=".hydra",
        log=log,
        log_before=(before.st_size, before.st_mtime_ns) if before else None,
    )


def _hydra_writes(path: Path, log: str = "train.log") -> None:
    """What Hydra writes into a run folder before the command starts: its record and the log."""
    (path / ".hydra").mkdir()
    (path / ".hydra" / "config.yaml").write_text("seed: 0\n")
    with open(path / log, "a") as f:
        f.write("[INFO] started\n")


def test_make_folders_returns_the_folders_it_made_outermost_first(tmp_path):
    (tmp_path / "a").mkdir()
    made = make_folders(tmp_path / "a" / "b" / "c", "hydra.run.dir", "a/b/c")
    assert made == [tmp_path / "a" / "b", tmp_path / "a" / "b" / "c"]
    assert make_folders(tmp_path / "a" / "b" / "c", "hydra.run.dir", "a/b/c") == []  # all there now
    assert [p.name for p in (tmp_path / "a" / "b" / "c").iterdir()] == []  # the write probe is gone


def test_make_folders_names_the_key_when_a_file_is_in_the_way(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(OutputError, match=r"paths.output_root=o: .*/f is a file, not a directory"):
        make_folders(tmp_path / "f" / "run", "paths.output_root", "o")


def test_make_folders_leaves_nothing_when_it_cannot_write(tmp_path):
    (tmp_path / "ro").mkdir()
    os.chmod(tmp_path / "ro", 0o500)
    try:
        if os.access(tmp_path / "ro", os.W_OK):  # root writes anyway (/proc is the fault matrix's case for root)
            pytest.skip("running as root")
        with pytest.raises(OutputError, match="hydra.run.dir=x: cannot create"):
            make_folders(tmp_path / "ro" / "x" / "y", "hydra.run.dir", "x")
    finally:
        os.chmod(tmp_path / "ro", 0o700)
    assert not (tmp_path / "ro" / "x").exists()


def test_undo_removes_the_record_and_the_folders_it_made_but_not_the_parent_it_found(tmp_path):
    (tmp_path / "outputs").mkdir()
    run = tmp_path / "outputs" / "train" / "day" / "run"
    made = make_folders(run, "hydra.run.dir", str(run))
    folder = _record(run, made)
    _hydra_writes(run)
    (run / "plots").mkdir()  # an empty folder the command made before it failed
    assert folder.undo()
    assert [p.name for p in tmp_path.iterdir()] == ["outputs"] and not list((tmp_path / "outputs").iterdir())


def test_undo_in_a_folder_of_the_users_leaves_exactly_what_was_there(tmp_path):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "server.log").write_text("the user's\n")
    (mine / "train.log").write_text("the user's own train.log\n")
    os.utime(mine / "train.log", ns=(10**18, 10**18))
    folder = _record(mine, make_folders(mine, "hydra.run.dir", "mine"))
    _hydra_writes(mine)
    assert folder.undo()
    assert sorted(p.name for p in mine.iterdir()) == ["server.log", "train.log"]
    assert (mine / "train.log").read_text() == "the user's own train.log\n"
    assert (mine / "train.log").stat().st_mtime_ns == 10**18


def test_undo_keeps_what_the_command_wrote(tmp_path):
    run = tmp_path / "run"
    folder = _record(run, make_folders(run, "hydra.run.dir", "run"))
    _hydra_writes(run)
    (run / "summary.json").write_text("{}")
    assert not folder.undo()
    assert sorted(p.name for p in run.iterdir()) == [".hydra", "summary.json", "train.log"]


def test_undo_puts_a_backup_back(tmp_path):
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "best.ckpt").write_bytes(b"old model")
    (run / "backup-20260101-000000").mkdir()  # an earlier overwrite's backup stays where it is
    assert holds_run(run) == "checkpoints/best.ckpt"
    backup, moved = move_to_backup(run)
    assert moved == ["checkpoints"] and backup.parent == run and backup.name.startswith("backup-")
    assert holds_run(run) is None and (backup / "checkpoints" / "best.ckpt").read_bytes() == b"old model"
    folder = _record(run, [])
    folder.backup, folder.moved = backup, moved
    _hydra_writes(run)
    assert folder.undo()
    assert sorted(p.name for p in run.iterdir()) == ["backup-20260101-000000", "checkpoints"]
    assert (run / "checkpoints" / "best.ckpt").read_bytes() == b"old model"


def test_what_marks_a_run_or_a_sweep(tmp_path):
    assert holds_run(tmp_path / "nowhere") is None
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "lorenz3.ckpt").write_bytes(b"")  # an export folder is not a run
    assert holds_run(tmp_path) is None
    (tmp_path / "sweep" / "3" / ".hydra").mkdir(parents=True)
    assert holds_run(tmp_path / "sweep") is None and holds_run(tmp_path / "sweep", sweep=True) == "3/.hydra"
    (tmp_path / "summary.json").write_text("{}")
    assert holds_run(tmp_path) == "summary.json"
