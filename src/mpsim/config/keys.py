"""What an override's key says about a run: where it writes, which hardware it uses, when it stops (none of which is
what it computes), and the key of a `key=value` override."""

from __future__ import annotations


def override_key(arg: str) -> str:
    """The key of a command-line override (`+a.b=1`, `~a.b`, `a.b=1` -> `a.b`)."""
    return arg.split("=", 1)[0].lstrip("+~")


def split_override(arg: str) -> tuple[str, str]:
    """An override as its key (without a leading `+` or `~`) and its value (`""` where it has none)."""
    key, _, value = arg.partition("=")
    return key.lstrip("+~"), value


def output_only(key: str) -> bool:
    """An override that says where or how a run writes (`paths.*`, `overwrite`) or how it shows progress, not what it
    computes: it may change when a run resumes, and runs that differ only in it are the same experiment in a report."""
    return (
        key == "paths"
        or key.startswith("paths.")
        or key in {"trainer.progress", "trainer.log_every", "trainer.log_every_s", "overwrite"}
    )


def host_only(key: str) -> bool:
    """An override that says which hardware a run computes on (`device`, `threads`), not what it computes: the
    same model, data and optimiser, rounded by other arithmetic. A run started on a GPU may resume on a CPU
    (and back) with it; its curve then continues, but not bitwise as one device alone would have made it."""
    return key in {"device", "threads"}


def stopping_rule(key: str) -> bool:
    """An override that says when training stops (`trainer.max_epochs`, `trainer.early_stop_patience`), not what
    an epoch computes: a resumed run may change it, so a run can be trained on past its first budget. Its curve
    up to where it would have stopped is the same either way."""
    return key in {"trainer.max_epochs", "trainer.early_stop_patience"}
