"""Atomic file writes: readers (and concurrent sweep jobs) never see half a file.

Files are created with the permissions the user's umask gives a plain `open()` (0644 under the usual 022;
`tempfile.mkstemp` alone would make them 0600), and a file that is replaced keeps its mode. A write that fails
(permissions, read-only file system, full disk) leaves the previous file untouched, no temporary file behind,
and raises `OutputError` naming the file.

A process killed outright (kill -9, a lost node) cannot remove its temporary file. Each temporary file's name says
which process wrote it (`.<name>.mpsim-<pid>-<host>.<random>.tmp`, host: a hash of the host name), so the next write
into that folder removes it once it is clearly orphaned: written on this host, by a process that no longer exists,
and untouched for `STALE_TMP_AGE_S` seconds. A live writer's file (a parallel sweep job's) is never touched, nor a
file from another host.
"""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import math
import os
import re
import shutil
import signal
import socket
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mpsim.errors import OutputError

log = logging.getLogger("mpsim")

_UNSAFE = re.compile(r"[^A-Za-z0-9_.-]")
_HOST = hashlib.sha256(socket.gethostname().encode()).hexdigest()[:8]
_TMP_NAME = re.compile(r"^\..+\.mpsim-(\d+)-([0-9a-f]{8})\.[A-Za-z0-9_]+\.tmp$")
STALE_TMP_AGE_S = 600  # a temporary file untouched this long, whose process is gone, is an orphan
_swept: set[str] = set()  # folders already cleared of orphaned temporary files by this process


def current_umask() -> int:
    """The process umask, read without changing it where the OS allows (Linux: /proc/self/status)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def describe_os_error(err: BaseException) -> str:
    """A short reason for a failed write, with the usual fix."""
    code = getattr(err, "errno", None)
    if code == errno.ENOSPC:
        return "the disk is full; free space or write elsewhere (paths.output_root=..., paths.ckpt_dir=...)"
    if code in (errno.EACCES, errno.EPERM):
        return "permission denied; fix the directory's permissions or choose another location"
    if code == errno.EROFS:
        return "the file system is read-only; choose a writable location"
    lines = str(err).splitlines()
    return str(getattr(err, "strerror", None) or (lines[0] if lines else type(err).__name__))


def atomic_write(path: str | Path, write: Any, mode: str = "wb") -> Path:
    """Write through a temporary sibling file and `os.replace` it into place.

    Args:
        path: destination.
        write: callable receiving the open temporary file object.
        mode: "wb" or "w".

    Raises:
        OutputError: the directory or file cannot be written (the previous file, if any, is untouched).
    """
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_orphaned_temps(path.parent)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.mpsim-{os.getpid()}-{_HOST}.", suffix=".tmp", dir=path.parent)
        try:
            file_mode = path.stat().st_mode & 0o7777 if path.exists() else 0o666 & ~current_umask()
            os.fchmod(fd, file_mode)
        except OSError:
            pass
        with _sigint_deferred():  # Ctrl-C mid-write would leave torch.save's zip writer broken: it waits for the file
            with os.fdopen(fd, mode) as f:
                write(f)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
    except BaseException as err:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(err, OSError) and not isinstance(err, OutputError):
            raise OutputError(f"cannot write {path}: {describe_os_error(err)}.") from None
        if isinstance(err, RuntimeError) and "writ" in str(err).lower():  # torch.save's stream writer
            raise OutputError(f"cannot write {path}: {str(err).splitlines()[0]} (full disk?).") from None
        raise
    return path


def remove_orphaned_temps(folder: Path, max_age_s: float = STALE_TMP_AGE_S) -> list[Path]:
    """Remove the temporary files that an mpsim process killed mid-write left in `folder`: named by
    `atomic_write` on this host, by a process that no longer runs, and older than `max_age_s`. Looks once per
    folder and process. Returns the files removed."""
    key = str(folder.absolute())
    if key in _swept:
        return []
    _swept.add(key)
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return []
    for entry in entries:
        match = _TMP_NAME.match(entry.name)
        if match is None or match.group(2) != _HOST or _process_exists(int(match.group(1))):
            continue
        try:
            if entry.is_file(follow_symlinks=False) and time.time() - entry.stat().st_mtime > max_age_s:
                os.unlink(entry.path)
                removed.append(Path(entry.path))
        except OSError:
            continue  # gone already (another process cleared it), or not ours to remove
    if removed:
        log.info(f"removed {len(removed)} temporary file(s) left in {folder} by an mpsim process that was killed")
    return removed


def _process_exists(pid: int) -> bool:
    """Whether a process with this id runs on this host (one we may not signal counts as running)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (OSError, OverflowError, ValueError):
        return True  # another user's process, or an id this system cannot check: keep its file
    return True


@contextmanager
def _sigint_deferred() -> Iterator[None]:
    """Hold a SIGINT (Ctrl-C) that arrives inside the block and deliver it, to the handler in force before, once the
    block is done. An interrupt inside `torch.save` raised in its zip writer, whose clean-up then failed with a
    RuntimeError that hid the interrupt (exit 1 and a traceback instead of 130 and the resume hint). Outside the
    main thread signals cannot be handled, and the block runs as is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous if previous is not None else signal.SIG_DFL)
        if held:
            signal.raise_signal(signal.SIGINT)


def safe_name(name: Any, fallback: str = "model") -> str:
    """A file name derived from data (e.g. a system name read from a file) reduced to ``[A-Za-z0-9_.-]``.

    Path separators and other characters become ``_``; leading dots are dropped, so the result is never
    ``..``, hidden, or a path. Empty results become `fallback`.
    """
    text = re.sub(r"\.{2,}", ".", _UNSAFE.sub("_", str(name))).strip("._")
    return text[:128] or fallback


def child_path(directory: str | Path, name: str) -> Path:
    """`directory / name` where `name` is checked to stay inside `directory` (no separators, no ``..``)."""
    directory = Path(directory)
    out = directory / name
    if name != safe_name(name) or out.resolve().parent != directory.resolve():
        raise OutputError(f"refusing to write {name!r}: it would leave {directory}.")
    return out


def keep_previous(path: str | Path) -> Path:
    """Keep the file at `path` recoverable before it is replaced: a hard link (or copy) named
    ``<stem>.<its modification time>[-k]<suffix>`` beside it. Returns that name."""
    path = Path(path)
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(path.stat().st_mtime))
    backup, k = path.with_name(f"{path.stem}.{stamp}{path.suffix}"), 1
    while backup.exists():
        backup, k = path.with_name(f"{path.stem}.{stamp}-{k}{path.suffix}"), k + 1
    try:
        os.link(path, backup)
    except OSError:
        try:
            shutil.copy2(path, backup)
        except OSError as err:
            raise OutputError(
                f"cannot keep the previous {path} as {backup.name}: {describe_os_error(err)}; nothing was replaced."
            ) from None
    return backup


def json_default(obj: Any) -> Any:
    """`json.dump` fallback for tensors, arrays and numpy scalars."""
    if isinstance(obj, torch.Tensor | np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON-serialisable: {type(obj).__name__}")


def _clean(obj: Any) -> Any:
    """NaN/inf become null so that the JSON is standard."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_clean(v) for v in obj]
    return obj


def file_sha256(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes, read in 1 MiB blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def write_json(path: str | Path, data: Any) -> Path:
    """Write `data` as indented standard JSON (NaN → null), atomically."""
    text = json.dumps(_clean(json.loads(json.dumps(data, default=json_default))), indent=2)
    return atomic_write(path, lambda f: f.write(text + "\n"), mode="w")
