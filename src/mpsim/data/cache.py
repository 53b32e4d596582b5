"""Dataset cache keyed by a hash of everything that determines the data.

Simulating ground truth is the slow part of a short run, and sweeps regenerate the same data many times.
Entries are `.npz` files named by the SHA-256 of a canonical JSON key; writes are atomic and guarded by an
advisory file lock, so concurrent sweep jobs build each dataset once and never read half a file.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from mpsim.data.io import load_npz, save_npz
from mpsim.data.trajectories import Trajectories
from mpsim.errors import DataError
from mpsim.files import json_default

try:  # POSIX advisory locks; elsewhere the atomic rename alone keeps entries whole
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]

log = logging.getLogger(__name__)

CACHE_VERSION = 1  # bump when the way data is generated changes


def cache_key(spec: dict[str, Any]) -> str:
    """Hex digest (16 chars) of the canonical JSON of `spec` plus the cache version."""
    text = json.dumps({"v": CACHE_VERSION, **spec}, sort_keys=True, default=json_default)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as handle:
        if fcntl is not None:
            fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            if fcntl is not None:
                fcntl.flock(handle, fcntl.LOCK_UN)


def cached(cache_dir: str | Path | None, spec: dict[str, Any], build: Callable[[], Trajectories]) -> Trajectories:
    """Return the dataset described by `spec`, building and storing it on a miss.

    Args:
        cache_dir: cache directory (None: no caching).
        spec: everything that determines the data (system config, sizes, seeds, tolerances).
        build: makes the data on a miss.
    """
    if cache_dir is None:
        return build()
    cache_dir = Path(cache_dir)
    key = cache_key(spec)
    path = cache_dir / f"{key}.npz"
    with _locked(cache_dir / f"{key}.lock"):
        if path.is_file():
            try:
                data = load_npz(path)
                log.debug(f"dataset cache hit {path.name}")
                return data
            except DataError as err:  # a damaged entry is rebuilt, not trusted
                log.warning(f"dataset cache entry {path} is unreadable ({err}); rebuilding it")
        data = build()
        save_npz(data, path)
        with contextlib.suppress(OSError):
            (cache_dir / f"{key}.json").write_text(json.dumps(spec, indent=1, default=json_default))
        return data
