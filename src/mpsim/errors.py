"""Error kinds that end a command with one clear message and a non-zero exit.

Each message says what was wrong, where (file, row, column, config key) and how to fix it. The CLI prints
the message without a traceback; anything that is not an `MpsimError` is a bug and keeps its traceback.

Exit codes (documented in docs/guarantees.md and the README, "What mpsim guarantees"):

| code | meaning |
|---|---|
| 0 | success |
| 1 | a bug in mpsim (the traceback is printed) |
| 2 | bad input: config, data file, checkpoint, impossible model/system pairing |
| 3 | training or a rollout diverged (NaN/inf) |
| 4 | an output could not be written (permissions, read-only file system, full disk) |
| 5 | the job would not fit in memory (estimate refused before starting; `memory_check=false` overrides) |
| 130 | interrupted (Ctrl-C); `resume=true` continues |
"""

import difflib
from collections.abc import Sequence

EXIT_CODES = {
    0: "success",
    1: "bug (traceback)",
    2: "bad input",
    3: "diverged",
    4: "cannot write output",
    5: "not enough memory",
    130: "interrupted",
}


class MpsimError(Exception):
    """Base class: a user-facing error with a message that names the fix."""

    exit_code = 2


class ConfigError(MpsimError, ValueError):
    """A config value is unknown, of the wrong type, or contradicts another one."""


class DataError(MpsimError, ValueError):
    """A data file or array is malformed (NaN, ragged time grid, wrong columns, bad node ids)."""


class CheckpointError(MpsimError, ValueError):
    """A checkpoint is missing, unreadable, unsafe, or does not fit the model or system asked for."""


class IncompatibleError(MpsimError, ValueError):
    """A model cannot run on the chosen system (state/control size, graph kind, ...)."""


class DivergenceError(MpsimError, RuntimeError):
    """A rollout produced NaN/inf or the ODE solver's step size underflowed."""

    exit_code = 3


class OutputError(MpsimError, OSError):
    """An output file or directory cannot be written (permissions, read-only file system, full disk)."""

    exit_code = 4


class ResourceError(MpsimError, MemoryError):
    """The job would not fit in the memory available (estimated before it starts)."""

    exit_code = 5


def did_you_mean(name: str, choices: Sequence[str]) -> str:
    """ " Did you mean 'x'?" for the closest of `choices` to a misspelt `name` (empty when none is close)."""
    same_letters = [c for c in choices if c.lower() == name.lower() and c != name]
    close = same_letters[:2] or difflib.get_close_matches(name, list(choices), n=2)
    return f" Did you mean {' or '.join(repr(c) for c in close)}?" if close else ""
