"""Bounded reading of the YAML and JSON files mpsim takes from users and from run folders.

Every such file is read here, and refused with one message naming the file, the limit and the fix before it can
hang mpsim or exhaust its memory or stack:

- only a regular file is opened (a named pipe, a device or a socket is refused without opening it: reading one
  would block or never end);
- its size is checked before it is read (`SPEC_BYTES`, `RECORD_BYTES`, `META_BYTES`, `SUMMARY_BYTES`);
- its nesting is checked before it is parsed: JSON by a scan of its brackets (outside strings) before
  `json.loads` recurses, YAML while its nodes are composed (`MAX_DEPTH` levels);
- YAML anchors and aliases (`&a` / `*a`) may repeat at most `ALIAS_NODES` values in all, counted while the
  document is composed, so a "billion laughs" file (nine levels of aliases, a few hundred bytes) is refused after a
  few thousand steps instead of expanding into billions of values; an alias inside the node it names is refused.

YAML is read as plain data only (`yaml.SafeLoader`: a tag that would build an object is an error). Syntax errors
are the caller's to word (`yaml.YAMLError`, `json.JSONDecodeError`, `UnicodeDecodeError` and `OSError` pass
through); the limits raise `InputLimitError`, and a path that is not a regular file raises `DataError`.
"""

from __future__ import annotations

import json
import os
import re
import stat
from pathlib import Path
from typing import Any

import yaml

from mpsim.errors import DataError

MIB = 1 << 20
#: an equations spec (`model.spec=` / `system.spec=`)
SPEC_BYTES = 1 * MIB
#: a run's own records: `.hydra/config.yaml`, `.hydra/overrides.yaml`, `data.json`
RECORD_BYTES = 1 * MIB
#: a data file's metadata: the `meta` string of an `.npz`, the `<stem>.json` beside a CSV
META_BYTES = 8 * MIB
#: a run's `summary.json` (read by `mpsim report` and `mpsim bench`), a checkpoint's metric history
SUMMARY_BYTES = 16 * MIB
#: levels of nested lists and mappings in any YAML or JSON file
MAX_DEPTH = 64
#: values that YAML aliases may repeat in one file, in all (a value inside a repeated list counts each time)
ALIAS_NODES = 10_000

_JSON_STRING = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"', re.S)
_NOT_BRACKET = re.compile(r"[^\[\]{}]+")


class InputLimitError(DataError):
    """A file is larger, more deeply nested, or expands more YAML aliases than mpsim reads."""


class _Limit(Exception):
    """Raised inside the YAML composer; `load_yaml` words it with the file's name."""


def size_text(n: int) -> str:
    """`n` bytes as the user reads a limit: 1 MB, 16 MB, 0.3 MB (MB = 2**20 bytes), 12.5 kB below 0.1 MB."""
    return f"{n / MIB:.3g} MB" if n >= MIB // 10 else f"{n / 1024:.3g} kB"


def not_a_regular_file(path: str | Path) -> str | None:
    """Why `path` cannot be read as a file (it does not exist, is a folder, a named pipe, ...), or None when it is
    a regular file (or a link to one). Never opens it."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "does not exist"
    except OSError as err:
        return f"cannot be read ({err.strerror or err})"
    if stat.S_ISREG(mode):
        return None
    if stat.S_ISDIR(mode):
        return "is a folder, not a file"
    kind = (
        "a named pipe (FIFO)"
        if stat.S_ISFIFO(mode)
        else "a socket"
        if stat.S_ISSOCK(mode)
        else "a device"
        if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
        else "a special file"
    )
    return f"is {kind}, not a regular file"


def read_text(path: str | Path, limit: int, where: str, fix: str) -> str:
    """The text of the regular file `path`, at most `limit` bytes (UTF-8).

    Args:
        path: the file.
        limit: the most bytes it may hold.
        where: how messages name it ("spec file /a/b.yaml").
        fix: what the user can do about a file over the limit (a sentence without its final dot).

    Raises:
        DataError: not a regular file (checked without blocking on a named pipe).
        InputLimitError: larger than `limit`.
        OSError, UnicodeDecodeError: it cannot be read, or is not UTF-8 text.
    """
    why = not_a_regular_file(path)
    if why is not None and why != "does not exist":
        raise DataError(f"{where} {why}.")
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))  # a pipe swapped in: no block
    with os.fdopen(fd, "rb") as handle:
        info = os.fstat(handle.fileno())
        if not stat.S_ISREG(info.st_mode):
            raise DataError(f"{where} is not a regular file; give a regular file.")
        if info.st_size > limit:
            raise _too_large(where, info.st_size, limit, fix)
        data = handle.read(limit + 1)
    if len(data) > limit:  # it grew while being read
        raise _too_large(where, len(data), limit, fix)
    return data.decode("utf-8")


def _too_large(where: str, size: int, limit: int, fix: str) -> InputLimitError:
    return InputLimitError(
        f"{where} is {size_text(size)}, over mpsim's limit of {size_text(limit)} for this file. {fix}."
    )


# ---- JSON ------------------------------------------------------------------------------------------------------
def json_depth(text: str) -> int:
    """The deepest nesting of lists and objects in JSON `text`, from its brackets outside strings (no parsing, no
    recursion: a file of 100 000 `[` is measured in milliseconds)."""
    import numpy as np

    brackets = _NOT_BRACKET.sub("", _JSON_STRING.sub("", text))
    codes = np.frombuffer(brackets.encode("ascii"), dtype=np.uint8)
    step = np.where((codes == ord("[")) | (codes == ord("{")), 1, -1).astype(np.int32)
    return int(np.cumsum(step).max(initial=0))


def parse_json(text: str, where: str, fix: str, limit: int) -> Any:
    """`json.loads(text)` once its size (`limit` bytes) and depth (`MAX_DEPTH`) are checked.

    Raises:
        InputLimitError: too large or too deeply nested (named by `where`, with `fix`).
        json.JSONDecodeError: not valid JSON.
    """
    size = len(text) if text.isascii() else len(text.encode("utf-8", "replace"))
    if size > limit:
        raise _too_large(where, size, limit, fix)
    depth = json_depth(text) if text.count("[") + text.count("{") > MAX_DEPTH else 0
    if depth > MAX_DEPTH:
        raise InputLimitError(
            f"{where} nests lists or objects {depth:,} levels deep, over mpsim's limit of {MAX_DEPTH}; flatten it. "
            f"{fix}."
        )
    return json.loads(text)


def load_json(path: str | Path, limit: int, where: str, fix: str) -> Any:
    """The JSON value in the regular file `path`, size and depth checked before it is parsed (`parse_json`)."""
    return parse_json(read_text(path, limit, where, fix), where, fix, limit)


# ---- YAML ------------------------------------------------------------------------------------------------------
class BoundedLoader(yaml.SafeLoader):
    """`yaml.SafeLoader` that refuses, while composing, nesting deeper than `MAX_DEPTH` and aliases that repeat
    more than `ALIAS_NODES` values in all (an alias counts the values of the node it names, aliases inside it
    included)."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0
        self._composed = 0  # values composed so far, each alias counted as the values it repeats
        self._repeated = 0  # of those, values repeated by aliases
        self._sizes: dict[int, int] = {}  # id(anchored node) -> its values, once complete

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            mark = self.peek_event().start_mark
            node = super().compose_node(parent, index)
            size = self._sizes.get(id(node))
            if size is None:
                raise _Limit(f"the alias at line {mark.line + 1} names a node that contains it (a loop); remove it")
            self._composed += size
            self._repeated += size
            if self._repeated > ALIAS_NODES:
                raise _Limit(
                    f"its anchors and aliases (&name, *name) repeat more than {ALIAS_NODES:,} values by line "
                    f"{mark.line + 1}, mpsim's limit (against 'billion laughs' files); write the values out instead"
                )
            return node
        event = self.peek_event()
        if self._depth >= MAX_DEPTH and not isinstance(event, yaml.ScalarEvent):
            raise _Limit(
                f"lists or mappings nest more than {MAX_DEPTH} levels deep by line {event.start_mark.line + 1}, "
                "mpsim's limit; flatten them"
            )
        self._depth += 1
        before = self._composed
        node = super().compose_node(parent, index)
        self._depth -= 1
        self._composed += 1
        if event.anchor is not None:
            self._sizes[id(node)] = self._composed - before
        return node


def parse_yaml(text: str, where: str, fix: str, loader: type[BoundedLoader] = BoundedLoader) -> Any:
    """The plain data in YAML `text`, read with `loader` (a `BoundedLoader`).

    Raises:
        InputLimitError: nested too deeply or too many values repeated by aliases.
        yaml.YAMLError: not valid YAML, or a tag that is not plain data.
    """
    try:
        return yaml.load(text, Loader=loader)  # noqa: S506 (a SafeLoader)
    except _Limit as limit:
        raise InputLimitError(f"{where}: {limit}. {fix}.") from None


def load_yaml(path: str | Path, limit: int, where: str, fix: str, loader: type[BoundedLoader] = BoundedLoader) -> Any:
    """The plain data in the regular YAML file `path`: size checked before it is read (`read_text`), nesting and
    aliases while it is composed (`parse_yaml`)."""
    return parse_yaml(read_text(path, limit, where, fix), where, fix, loader)
