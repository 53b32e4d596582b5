"""`mpsim train resume=...`: the command line that continues an earlier run, made before Hydra starts.

`with_resume` points Hydra's run directory at the run that `resume=` names (`resume=<run directory>`) or finds
(`resume=true`: `find_resumable`), with that run's own overrides; overrides given now that would change what the
run computes are refused. Imported by `mpsim.cli` only; torch is imported only to hash a moved data file.
"""

from __future__ import annotations

import re
import sys
from collections.abc import Callable
from pathlib import Path

from mpsim.config.keys import host_only, output_only, override_key, split_override, stopping_rule
from mpsim.config.records import read_overrides_file
from mpsim.errors import MpsimError
from mpsim.safeload import RECORD_BYTES, load_json

TRUE = {"true", "yes", "1", "on"}


def _own(args: list[str]) -> list[str]:
    """The overrides that define a run (not `resume` or `overwrite`, not Hydra's own settings)."""
    return [
        a
        for a in args
        if not override_key(a).startswith(("resume", "hydra", "overwrite")) and a not in ("-m", "--multirun")
    ]


def find_resumable(args: list[str], command: str = "train") -> Path | None:
    """The newest earlier run of `mpsim <command>` with the same overrides (ignoring `resume` and when training
    stops: `trainer.max_epochs=` raised with resume=true trains the same run further) that has a `last.ckpt`,
    under `paths.output_root`."""

    def defining(overrides: list[str]) -> list[str]:
        return sorted(a for a in _own(overrides) if not stopping_rule(override_key(a)))

    key = defining(args)
    root = next((a.split("=", 1)[1] for a in args if a.startswith("paths.output_root=")), "outputs")
    found = []
    for overrides in Path(root).glob(f"{command}/*/*/.hydra/overrides.yaml"):
        run = overrides.parent.parent
        try:
            saved = read_overrides_file(run)
        except MpsimError:
            continue  # a damaged record matches nothing; resume=<that run> names the damage
        last = run / "checkpoints" / "last.ckpt"
        if saved is not None and defining(saved) == key and last.is_file():
            found.append((last.stat().st_mtime, run))
    return max(found)[1] if found else None


def with_resume(args: list[str]) -> list[str]:
    """Point Hydra's run directory at the run that `resume=` continues, with that run's own overrides.

    The resumed run keeps its `.hydra/` record (nothing is rewritten there). Overrides that differ from the
    run's own (other data, another learning rate, ...) are refused: they would silently change the run. Where it
    writes (`paths.*`) and how it shows its progress (`trainer.progress`, `trainer.log_every[_s]`) are not what it
    computes: those given now replace the run's own, so a run directory moved to another disk or machine resumes
    there, and a run started with a bar can be resumed in the background without one. Nor is the hardware it
    computes on (`device`, `threads`): a run started on a GPU resumes on a CPU with device=cpu. Nor is when it
    stops (`trainer.max_epochs`, `trainer.early_stop_patience`): a finished run trains on with a larger
    `trainer.max_epochs` (the trainer refuses fewer epochs than the run has already run). `data.path` may
    differ too when the file holds the bytes the run trained on (the SHA-256 it recorded in `data.json`, or the
    file at its own path): data moved along with its run.
    """
    value = _resume_value(args)
    if value is None:
        return args
    run = _run_to_resume(args, value)
    own = _overrides_to_resume(run, args, value)
    print(f"mpsim train: resuming {run}", file=sys.stderr)
    hydra_args = [a for a in args if override_key(a).startswith("hydra")]
    return [*own, *hydra_args, f"resume={value}", f"hydra.run.dir={run.resolve()}", "hydra.output_subdir=null"]


def _resume_value(args: list[str]) -> str | None:
    """The last `resume=` value, or None where the command does not resume (no `resume=`, or false)."""
    values = [a.split("=", 1)[1] for a in args if a.startswith("resume=")]
    if not values or values[-1].lower() in {"false", "no", "0", "off", "null"}:
        return None
    if "-m" in args or "--multirun" in args:
        raise MpsimError("resume works for single runs; resume each sweep job with resume=<its run directory>.")
    return values[-1]


def _run_to_resume(args: list[str], value: str) -> Path:
    """The run directory that `resume=<value>` names (`true`: the newest matching run), which holds a last.ckpt."""
    if value.lower() in TRUE:
        run = find_resumable(args)
        if run is None:
            shown = " ".join(a for a in args if not a.startswith("resume="))
            raise MpsimError(
                f"resume=true: no earlier run of `mpsim train {shown}` with a checkpoints/last.ckpt under "
                "outputs/train. Run it without resume=true first, or pass resume=<run directory>."
            )
        return run
    run = Path(value)
    if not (run / "checkpoints" / "last.ckpt").is_file():
        raise MpsimError(
            f"resume={value}: {run}/checkpoints/last.ckpt does not exist. Pass the directory of an "
            "earlier train run (it holds checkpoints/last.ckpt)."
        )
    return run


def _overrides_to_resume(run: Path, args: list[str], value: str) -> list[str]:
    """The overrides the resumed run continues with: its own, with those given now that may differ (where it writes
    and runs, when it stops, a moved data file) in their place."""
    saved = read_overrides_file(run)  # a damaged record is refused here, by name (a DataError)
    if saved is None:
        print(
            f"mpsim train: warning: {run}/.hydra/overrides.yaml is missing; resuming with the overrides given "
            "now, which cannot be checked against the run's own.",
            file=sys.stderr,
        )
        return _own(args)
    mine, theirs = dict(split_override(a) for a in _own(args)), dict(split_override(a) for a in _own(saved))
    # the data file may have moved with the run (a copied results folder) if it holds the same bytes
    data_moved = (
        "data.path" in mine
        and "data.path" in theirs
        and mine["data.path"] != theirs["data.path"]
        and _same_data(run, mine["data.path"], theirs["data.path"])
    )

    def free(k: str) -> bool:  # may differ from the run's own: where it writes and runs, when it stops
        return output_only(k) or host_only(k) or stopping_rule(k) or (k == "data.path" and data_moved)

    _refuse_differences(run, value, saved, mine, theirs, free)
    moved = {k for k in mine if free(k)}
    for k in sorted(k for k in moved if host_only(k) and theirs.get(k, "its default") != mine[k]):
        print(
            f"mpsim train: resuming with {k}={mine[k]} (the run has {k}={theirs.get(k, 'its default')}): "
            "the same model, data and optimiser on other hardware; the curve continues, rounded differently.",
            file=sys.stderr,
        )
    kept = [a for a in _own(saved) if split_override(a)[0] not in moved]
    return kept + [a for a in _own(args) if split_override(a)[0] in moved]


def _refuse_differences(
    run: Path,
    value: str,
    saved: list[str],
    mine: dict[str, str],
    theirs: dict[str, str],
    free: Callable[[str], bool],
) -> None:
    """Refuse overrides given now (`mine`) that differ from the run's own (`theirs`) where they may not (`free`)."""
    differ = [
        f"{k}={v} (the run has {k}={theirs[k]}{_data_hint(run, theirs[k]) if k == 'data.path' else ''})"
        if k in theirs
        else f"{k}={v} (not set in the run)"
        for k, v in mine.items()
        if theirs.get(k) != v and not free(k)
    ]
    if differ:
        raise MpsimError(
            f"resume={value}: {'; '.join(differ)}. A resumed run continues with its own config "
            f"({' '.join(_own(saved)) or 'no overrides'}); drop the differing overrides, or start a new run "
            "without resume= (finetune from its checkpoint with init=<run>/checkpoints/best.ckpt)."
        )


def _recorded_data_digest(run: Path) -> str | None:
    """The SHA-256 of its data file that a run recorded in `<run>/data.json` (None if absent or malformed)."""
    try:  # a damaged, oversized or deeply nested record vouches for nothing
        record = load_json(run / "data.json", RECORD_BYTES, str(run / "data.json"), "Restore it")
    except (OSError, ValueError):
        return None
    digest = record.get("sha256") if isinstance(record, dict) else None
    return digest if isinstance(digest, str) and re.fullmatch(r"[0-9a-f]{64}", digest) else None


def _same_data(run: Path, new: str, old: str) -> bool:
    """Whether the file `new` holds the bytes the run trained on: the digest it recorded or, for a run that
    recorded none, the file at its own `data.path` if that is still there."""
    from mpsim.files import file_sha256  # imports torch: only on this path

    if not Path(new).is_file():
        return False
    recorded = _recorded_data_digest(run)
    if recorded is None:
        if not Path(old).is_file():
            return False
        recorded = file_sha256(old)
    return file_sha256(new) == recorded


def _data_hint(run: Path, old: str) -> str:
    """Why a different `data.path` was refused: the run's file is gone unrecorded, or the bytes differ."""
    if _recorded_data_digest(run) is None and not Path(old).is_file():
        return "; that file is gone and the run recorded no digest, so a moved copy cannot be checked"
    return "; a data file may move with its run only if it holds the same bytes"
