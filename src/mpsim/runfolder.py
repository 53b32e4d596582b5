"""The run folder of one mpsim command: what this invocation found there and what it made.

Hydra makes the run folder (`hydra.run.dir`), writes its `.hydra/` record and opens `<command>.log` there before
the command starts. `RunFolderCallback` (a Hydra callback, `hydra/output/mpsim.yaml`) runs just before that, on the
same composed config, so it resolves the folder exactly as Hydra will (`${now:...}` is resolved once per config and
cached). It then

- creates the folders that do not exist yet itself, and keeps their names (`RunFolder.created`): the real test that
  the location can be written (exit 4 naming the key to change), and the record of what a failure may remove;
- refuses a folder that already holds a run (a `.hydra/` record, a `summary.json`, a run's `checkpoints/best.ckpt`
  or `last.ckpt`) unless the command resumes it (`resume=`), or `overwrite=true` moves its files to
  `<folder>/backup-<time>/` first;
- notes what the folder held, so that a command that fails on a bad input removes exactly what this invocation added
  (`RunFolder.undo`): Hydra's record and log, then the folders it created, never a folder or file that was there
  before (a log that was there gets its old length back, a backup its old place).

`mpsim -m` sweeps get the same checks for `hydra.sweep.dir`. This module does not import torch.
"""

from __future__ import annotations

import os
import shlex
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from mpsim.errors import ConfigError, MpsimError, OutputError

BACKUP_PREFIX = "backup-"
#: what marks a folder as holding a run of mpsim (or of another Hydra program): its files would be replaced
RUN_MARKS = (".hydra", "summary.json", "multirun.yaml", "checkpoints/best.ckpt", "checkpoints/last.ckpt")
FALSE = {"false", "no", "0", "off", "null", "none", ""}


@dataclass
class RunFolder:
    """One run folder as this invocation found it (before Hydra wrote there) and what it made."""

    path: Path  # absolute
    created: list[Path]  # folders this invocation made, outermost first
    kept: set[str]  # entries of `path` before Hydra wrote there (after a backup)
    record: str | None  # Hydra's record folder (hydra.output_subdir, `.hydra`)
    log: str  # the command's log file name
    log_before: tuple[int, int] | None = None  # (size, mtime_ns) of a log that was there already
    backup: Path | None = None  # where overwrite=true moved the earlier files
    moved: list[str] = field(default_factory=list)

    def undo(self) -> bool:
        """After a failed command: remove what this invocation added, if that is only Hydra's record, the log and
        empty folders (a command that wrote results keeps them), put back a backup it made, and remove the folders
        it created if they are empty. Returns whether the folder is as it was before (False, with nothing more
        removed, where a step fails: the folder is then left as the command left it, or partly restored)."""
        try:
            return self._undo()
        except OSError:
            return False

    def _undo(self) -> bool:
        if not self.path.is_dir():
            return False
        added = [self.path / n for n in sorted(set(os.listdir(self.path)) - self.kept)]
        if not all(p.name in (self.record, self.log) or _holds_no_files(p) for p in added):
            return False
        for p in added:
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            else:
                p.unlink()
        if self.log_before is not None:  # a log that was there before: back to its old length and time
            size, mtime_ns = self.log_before
            os.truncate(self.path / self.log, size)
            os.utime(self.path / self.log, ns=(mtime_ns, mtime_ns))
        if self.backup is not None:
            for name in self.moved:
                os.replace(self.backup / name, self.path / name)
            self.backup.rmdir()
        for folder in reversed(self.created):
            try:
                folder.rmdir()
            except OSError:
                break
        return True


#: the run folder of the command running in this process (set by `RunFolderCallback.on_run_start`)
CURRENT: RunFolder | None = None


def take(output_dir: str | Path) -> RunFolder | None:
    """The record of the run folder `output_dir`, made for the command now running in this process (None in a
    sweep, or outside mpsim's Hydra configs); the record is handed out once."""
    global CURRENT
    folder, CURRENT = CURRENT, None
    return folder if folder is not None and folder.path == Path(output_dir).absolute() else None


class RunFolderCallback(Callback):
    """Hydra callback: check and record the run (or sweep) folder before Hydra writes anything there."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        global CURRENT
        CURRENT = None
        if _torchrun_rank() > 0:  # the other ranks of `torchrun` write nothing there (mpsim.__main__.worker_args)
            return
        HydraConfig.instance().set_config(config)  # for ${hydra:...} in the folder's name; run_job sets it again
        try:
            CURRENT = prepare(config, "hydra.run.dir")
        except MpsimError as err:
            _exit(config, err)

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        global CURRENT
        CURRENT = None
        try:
            prepare(config, "hydra.sweep.dir")
        except MpsimError as err:
            _exit(config, err)


def _exit(config: DictConfig, err: MpsimError) -> None:
    """One message and the error's exit code (a Hydra callback's exceptions would only become warnings)."""
    print(f"mpsim {OmegaConf.select(config, 'hydra.job.name')}: error: {err}", file=sys.stderr)
    sys.exit(err.exit_code)


def prepare(config: DictConfig, key: str) -> RunFolder:
    """Create the folder `key` (hydra.run.dir or hydra.sweep.dir) names, as Hydra will resolve it, and record what
    was there; refuse a folder that already holds a run (or back it up with overwrite=true).

    Raises:
        OutputError: the folder cannot be created or written.
        ConfigError: it already holds a run, and neither resume= nor overwrite=true was given.
    """
    path = Path(os.path.abspath(str(OmegaConf.select(config, key))))
    named, value = _named_key(config, key)
    existed = path.is_dir()
    created = make_folders(path, named, value)
    backup: Path | None = None
    moved: list[str] = []
    mark = None if _resuming(config) else holds_run(path, sweep=key == "hydra.sweep.dir")
    if existed and mark is not None:
        if not _true(config.get("overwrite")):
            raise ConfigError(_taken_message(config, key, named, value, path, mark))
        backup, moved = move_to_backup(path)
        print(
            f"mpsim {config.hydra.job.name}: overwrite=true: moved the {len(moved)} earlier entries of {path} to "
            f"{backup} (move them back to undo).",
            file=sys.stderr,
        )
    subdir = OmegaConf.select(config, "hydra.output_subdir")
    log = f"{OmegaConf.select(config, 'hydra.job.name')}.log"
    before = (path / log).stat() if (path / log).is_file() else None
    return RunFolder(
        path=path,
        created=created,
        kept=set(os.listdir(path)),
        record=Path(str(subdir)).parts[0] if subdir else None,
        log=log,
        log_before=(before.st_size, before.st_mtime_ns) if before is not None else None,
        backup=backup,
        moved=moved,
    )


def make_folders(path: Path, key: str, value: Any) -> list[Path]:
    """Create `path` and its missing parents one by one; return those this call made, outermost first, after
    checking that a file can be written in `path`.

    Raises:
        OutputError: naming `key`, where a folder cannot be made or written (permissions, a read-only or virtual
            file system such as /proc, a file in the way).
    """
    missing = []
    probe = path
    while not probe.exists() and probe != probe.parent:
        missing.append(probe)
        probe = probe.parent
    fix = f"Choose a writable directory: {key}=<dir>."
    if not probe.is_dir():
        raise OutputError(f"{key}={value}: {probe} is a file, not a directory. {fix}")
    created: list[Path] = []
    try:
        for folder in reversed(missing):
            try:
                folder.mkdir()
                created.append(folder)
            except FileExistsError:  # made at the same moment by another process (a parallel sweep job): not ours
                if not folder.is_dir():
                    raise
        fd, name = tempfile.mkstemp(prefix=".mpsim-probe-", dir=path)
        os.close(fd)
        os.unlink(name)
    except OSError as err:
        for folder in reversed(created):
            folder.rmdir()
        from mpsim.files import describe_os_error  # imports torch: only on this path

        reason = describe_os_error(err)
        if isinstance(err, FileNotFoundError):  # mkdir in an existing folder: /proc and other virtual file systems
            reason = f"{probe} does not take new folders (a virtual or read-only file system)"
        raise OutputError(f"{key}={value}: cannot create {path}: {reason}. {fix}") from None
    return created


def holds_run(path: Path, sweep: bool = False) -> str | None:
    """What marks `path` as a folder that already holds a run (for a sweep folder: a run in any job folder),
    or None."""
    if not path.is_dir():
        return None
    for mark in RUN_MARKS:
        if (path / mark).exists():
            return mark
    if sweep:
        for child in sorted(p for p in path.iterdir() if p.is_dir() and not p.name.startswith(BACKUP_PREFIX)):
            inner = holds_run(child)
            if inner is not None:
                return f"{child.name}/{inner}"
    return None


def move_to_backup(path: Path) -> tuple[Path, list[str]]:
    """Move every entry of `path` (except earlier backups) into a new `path/backup-<time>[-k]/`; return that folder
    and the names moved. Renames within one folder: nothing is copied or rewritten."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    backup, k = path / f"{BACKUP_PREFIX}{stamp}", 1
    while backup.exists():
        backup, k = path / f"{BACKUP_PREFIX}{stamp}-{k}", k + 1
    names = sorted(n for n in os.listdir(path) if not n.startswith(BACKUP_PREFIX))
    try:
        backup.mkdir()
        for name in names:
            os.replace(path / name, backup / name)
    except OSError as err:
        from mpsim.files import describe_os_error

        raise OutputError(
            f"overwrite=true: cannot move the earlier files of {path} to {backup}: {describe_os_error(err)}."
        ) from None
    return backup, names


def shown_path(path: Path) -> str:
    """`path` for a command line: relative to the current directory when inside it, quoted for the shell."""
    try:
        shown = str(path.relative_to(Path.cwd()))
    except ValueError:
        shown = str(path)
    return shlex.quote(shown)


def _holds_no_files(path: Path) -> bool:
    """A folder (tree) without a single file in it: made by the command, never written to."""
    return path.is_dir() and not path.is_symlink() and not any(p.is_file() or p.is_symlink() for p in path.rglob("*"))


def _named_key(config: DictConfig, key: str) -> tuple[str, Any]:
    """The setting to change for the folder `key`: `key` itself where it was given on the command line, else
    `paths.output_root`, which the default folder names start with."""
    given = [str(o) for o in OmegaConf.select(config, "hydra.overrides.hydra") or []]
    values = [o.split("=", 1)[1] for o in given if o.split("=", 1)[0].lstrip("+~") == key]
    if values or OmegaConf.select(config, "paths.output_root") is None:
        return key, values[-1] if values else OmegaConf.select(config, key)
    return "paths.output_root", OmegaConf.select(config, "paths.output_root")


def _torchrun_rank() -> int:
    """This process's rank under `torchrun` (0 without it)."""
    try:
        return int(os.environ.get("RANK", "0")) if int(os.environ.get("WORLD_SIZE", "1")) > 1 else 0
    except ValueError:
        return 0


def _true(value: Any) -> bool:
    return value is True or (isinstance(value, str) and value.lower() not in FALSE)


def _resuming(config: DictConfig) -> bool:
    """`mpsim train resume=...` continues the run in its own folder."""
    value = config.get("resume")
    return value is not None and value is not False and str(value).lower() not in FALSE


def _taken_message(config: DictConfig, key: str, named: str, value: Any, path: Path, mark: str) -> str:
    sweep = key == "hydra.sweep.dir"
    fresh = f"leave {key} out for a new timestamped one" if named == key else "a new timestamped one is made per run"
    fixes = [f"continue it with resume={shown_path(path)}"] if config.get("task") == "train" and not sweep else []
    fixes += [
        f"pick a new folder ({key}=<new folder>; {fresh})",
        f"add overwrite=true to move its files to {path}/{BACKUP_PREFIX}<time>/ first",
    ]
    first = ", ".join(fixes[:-1])
    return (
        f"{named}={value}: {path} already holds {'a sweep' if sweep else 'a run'} ({mark}); nothing was written. "
        f"{first[0].upper()}{first[1:]} or {fixes[-1]}."
    )
