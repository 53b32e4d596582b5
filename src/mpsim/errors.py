"""Error kinds that end a command with one clear message and a non-zero exit.

Each message says what was wrong, where (file, row, column, config key) and how to fix it. The CLI prints
the message without a traceback; anything that is not an `MpsimError` is a bug and keeps its traceback.
"""


class MpsimError(Exception):
    """Base class: a user-facing error with a message that names the fix."""

    exit_code = 2


class ConfigError(MpsimError, ValueError):
    """A config value is unknown, of the wrong type, or contradicts another one."""


class DataError(MpsimError, ValueError):
    """A data file or array is malformed (NaN, ragged time grid, wrong columns, bad node ids)."""


class CheckpointError(MpsimError, ValueError):
    """A checkpoint is missing, unreadable, or does not fit the model or system asked for."""


class IncompatibleError(MpsimError, ValueError):
    """A model cannot run on the chosen system (state/control size, graph kind, ...)."""


class DivergenceError(MpsimError, RuntimeError):
    """A rollout produced NaN/inf or the ODE solver's step size underflowed."""

    exit_code = 3
