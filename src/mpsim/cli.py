"""`mpsim <command> [hydra overrides]`: command dispatch only.

Hydra has no subcommands, so `main` pops the command word, rewrites `sys.argv` and calls that command's
`@hydra.main` wrapper, a thin shell around a plain `run_<command>(cfg) -> dict`. Before Hydra starts a run,
the command line is composed and checked (`mpsim.config.compose_command`; `resume=` is turned into the run's own
command line by `mpsim.resume`) without importing torch, so `--help`, typos and bad values answer at once and leave
no run directory behind. User-facing errors (`MpsimError`, and failed writes or allocations) end with one message on
stderr and the exit code of their kind (`mpsim.errors`); anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mpsim.errors import MpsimError, OutputError, ResourceError
from mpsim.process import configure_process

CONF_DIR = str(Path(__file__).parent / "conf")
log = logging.getLogger("mpsim")

USAGE = """usage: mpsim <command> [key=value ...] [-m] [--cfg job] [--help]

commands:
  train      train a model (mode=scratch), finetune it (init=<ckpt>) or evaluate it zero-shot (mode=zeroshot)
  eval       evaluate a checkpoint on a system or data file: mpsim eval init=<ckpt> system=<name>
  simulate   export ground-truth (and model) trajectories: mpsim simulate system=<name> format=npz|csv
  diagnose   find the effect a model lacks in data, add it, compare: mpsim diagnose init=<ckpt> fix=true
  report     tabulate run and sweep directories: mpsim report runs='[outputs/multirun]'
  bench      performance ratios measured side by side: mpsim bench bench=mpnode

examples:
  mpsim train                                      # default job: MP-NODE on two coupled pendulums
  mpsim train system=lorenz3                       # exports checkpoints/lorenz3.ckpt
  mpsim train system=lorenz10 init=lorenz3.ckpt    # finetune
  mpsim train -m system=lorenz10 data.n_train=50,100,500 init=lorenz3.ckpt,null
  mpsim train --help                               # every config group and option
"""


def _fail(command: str, err: MpsimError) -> None:
    """Print one message and exit with the error's code."""
    print(f"mpsim {command}: error: {err}", file=sys.stderr)
    sys.exit(err.exit_code)


def _as_user_error(err: BaseException) -> MpsimError | None:
    """Failed writes and allocations are the user's environment, not a bug: one message each."""
    if isinstance(err, MpsimError):
        return err
    if isinstance(err, OSError):
        from mpsim.files import describe_os_error

        where = f" {err.filename}" if getattr(err, "filename", None) else ""
        return OutputError(f"cannot write{where}: {describe_os_error(err)}.")
    text = str(err)
    if isinstance(err, MemoryError) or (
        isinstance(err, RuntimeError) and ("can't allocate memory" in text or "out of memory" in text.lower())
    ):
        first = text.strip().splitlines()[0][:200] if text.strip() else type(err).__name__
        return ResourceError(
            f"ran out of memory ({first}). Make the job smaller (fewer trajectories, shorter "
            "data.horizon, smaller trainer.batch_size or system) or use a machine with more memory."
        )
    return None


def _divergence_message(command: str, result: dict[str, Any]) -> str:
    best = result.get("best_epoch") or 0
    if best >= 1:
        kept = f"the best checkpoint so far (epoch {best}) was kept: {result.get('checkpoint')}"
        if result.get("exported"):
            kept += f", exported as {result['exported']}"
    else:
        kept = "no epoch finished, so there is no trained checkpoint (only the starting point in last.ckpt)"
    return (
        f"mpsim {command}: training diverged ({result.get('divergence') or 'NaN/inf'}); {kept}. "
        "Lower trainer.lr or trainer.clip_norm."
    )


def _interrupt_hint(command: str, run_dir: Path | None = None) -> str:
    """What a Ctrl-C leaves: `train` resumes from last.ckpt; the other commands start over (resume is train's).
    A run in a folder of its own choosing (`hydra.run.dir=`), or a sweep job, is named by its folder: `resume=true`
    finds only runs in the default folders."""
    from hydra.core.hydra_config import HydraConfig

    from mpsim.commands.runtime import hydra_overrides, is_multirun
    from mpsim.config.keys import override_key
    from mpsim.runfolder import shown_path

    if command != "train":
        return (
            "Every file it wrote is complete (files are written atomically, none half-written); "
            "run the same command again to redo it (resume= is for mpsim train)."
        )
    given = HydraConfig.initialized() and any(
        override_key(str(o)) == "hydra.run.dir" for o in HydraConfig.get().overrides.hydra
    )
    if run_dir is not None and (given or is_multirun()):
        return f"Completed epochs are saved in last.ckpt; continue with:\n  mpsim train resume={shown_path(run_dir)}"
    args = " ".join(a for a in hydra_overrides() if not a.startswith("resume="))
    return f"Completed epochs are saved in last.ckpt; continue with:\n  mpsim train {args} resume=true"


def _guard(command: str, func: Callable[[Any], dict], cfg: Any) -> dict | float | None:
    """Run a command; turn user errors into one message and an exit code. A fresh single run that fails (or is
    interrupted) before writing anything of its own leaves its folder as it was (`mpsim.runfolder`)."""
    from hydra.core.hydra_config import HydraConfig

    from mpsim import runfolder
    from mpsim.commands.runtime import is_multirun

    multirun = is_multirun()
    run_dir = Path(HydraConfig.get().runtime.output_dir) if HydraConfig.initialized() else None
    folder = runfolder.take(run_dir) if run_dir is not None else None
    if multirun or cfg.get("resume"):
        folder = None  # a sweep job's folder is the sweep's; a resumed run's folder is the run's own
    try:
        result = func(cfg)
    except KeyboardInterrupt:
        if folder is not None and folder.undo():
            hint = "Nothing was saved yet, and nothing of the run is left; run the same command again."
        else:
            hint = _interrupt_hint(command, run_dir)
        print(f"\nmpsim {command}: interrupted. {hint}", file=sys.stderr)
        sys.exit(130)
    except Exception as err:  # noqa: BLE001 - user errors become one message; bugs are re-raised
        user = _as_user_error(err)
        if user is None:
            raise
        if folder is not None:
            folder.undo()
        _fail(command, user)
    if isinstance(result, dict) and result.get("status") == "diverged" and not multirun:
        print(_divergence_message(command, result), file=sys.stderr)
        sys.exit(3)
    code = result.get("exit_code") if isinstance(result, dict) else None
    if code and not multirun:  # a verdict with its own exit code (mpsim diagnose), after every file is written
        sys.exit(int(code))
    if not multirun:
        return None
    objective = (result or {}).get("objective")
    if isinstance(objective, dict) and "value" in objective:  # train: the number a sweeper (Optuna) minimises
        return objective["value"]
    return {k: v for k, v in (result or {}).items() if isinstance(v, str | int | float)}


def _hydra_command(command: str) -> Callable[[], None]:
    """The `@hydra.main` wrapper of `mpsim <command>` around `mpsim.commands.<command>.run_<command>`."""

    def task(cfg: Any) -> Any:
        import importlib

        configure_process()  # again in the worker processes of a launcher (joblib, submitit); idempotent
        # imported here, so that `mpsim <command> --help` and `--cfg job` answer without importing torch
        func = getattr(importlib.import_module(f"mpsim.commands.{command}"), f"run_{command}")
        return _guard(command, func, cfg)

    def wrapper() -> None:
        import hydra

        hydra.main(version_base="1.3", config_path="conf", config_name=command)(task)()

    return wrapper


COMMANDS: dict[str, Callable[[], None]] = {
    name: _hydra_command(name) for name in ("train", "eval", "simulate", "report", "bench", "diagnose")
}


def _check_writable(cfg: Any, command: str) -> None:
    """Refuse at start (before any work) output locations that cannot be written. The run (or sweep) folder itself
    is made, and so tested, just before Hydra writes there (`mpsim.runfolder`)."""
    paths = cfg.get("paths")
    if paths is None:
        return
    targets = [("paths.output_root", paths.get("output_root"))]
    if command == "train" and cfg.get("export"):
        targets.append(("paths.ckpt_dir", paths.get("ckpt_dir")))
    for key, value in targets:
        if not value:
            continue
        path = Path(os.path.expanduser(str(value))).absolute()
        probe = path
        while not probe.exists() and probe != probe.parent:
            probe = probe.parent
        if not probe.is_dir():
            raise OutputError(f"{key}={value}: {probe} is a file, not a directory. Choose a directory: {key}=<dir>.")
        if not os.access(probe, os.W_OK | os.X_OK) or not _can_make_folder(probe):
            raise OutputError(
                f"{key}={value}: {probe} is not writable (permissions, or a read-only or virtual file system). "
                f"Choose a writable directory: {key}=<dir>."
            )


def _can_make_folder(parent: Path) -> bool:
    """Whether a folder can be made in `parent` (tried, then removed): `os.access` says yes for root on read-only
    and virtual file systems such as /proc."""
    import tempfile

    try:
        os.rmdir(tempfile.mkdtemp(prefix=".mpsim-probe-", dir=parent))
    except OSError:
        return False
    return True


def _check_spec_files(cfg: Any) -> None:
    """Refuse at once, before Hydra starts a run (and before torch is imported), a `system.spec=` / `model.spec=`
    file beyond the bounds mpsim reads (size, nesting, aliases: `mpsim.safeload`). Everything else about the spec
    is checked where it is used."""
    from mpsim.safeload import SPEC_BYTES, load_yaml, not_a_regular_file

    for key in ("system", "model"):
        node = cfg.get(key)
        spec = node.get("spec") if hasattr(node, "get") else None
        if not isinstance(spec, str):
            continue
        path = Path(os.path.expanduser(spec))
        if not_a_regular_file(path) is not None:
            continue  # missing, a folder, a pipe: named where the spec is read
        fix = "Give a spec of plain states, equations and params (limits: docs/equations.md)"
        try:
            load_yaml(path, SPEC_BYTES, f"spec file {path}", fix)
        except MpsimError:
            raise
        except Exception:  # noqa: BLE001 - unreadable or not YAML: the spec's reader names it with its own fix
            continue


def _check_data_names(cfg: Any) -> None:
    """Refuse at once, before Hydra makes a run folder, a `data.columns` / `data.observed` /
    `data.control_columns` name that the model's spec does not have (`mpsim.data.keys`). A model that comes from
    a checkpoint (`init=`) is checked once it is loaded."""
    from collections.abc import Mapping

    from omegaconf import OmegaConf

    from mpsim.data.keys import check_data_names
    from mpsim.safeload import SPEC_BYTES, load_yaml, not_a_regular_file

    data, model = cfg.get("data"), cfg.get("model")
    if data is None or model is None or not data.get("path") or cfg.get("init"):
        return
    spec = model.get("spec")
    if isinstance(spec, str):
        path = Path(os.path.expanduser(spec))
        if not_a_regular_file(path) is not None:
            return
        try:
            spec = load_yaml(path, SPEC_BYTES, f"spec file {path}", "")
        except Exception:  # noqa: BLE001 - the spec's reader names what is wrong with it
            return
    else:
        spec = OmegaConf.to_container(spec, resolve=True) if spec is not None else None
    spec = spec if isinstance(spec, Mapping) else {}
    states = model.get("states") or spec.get("states")
    inputs = model.get("inputs") or spec.get("inputs") or []
    outputs = model.get("outputs") or spec.get("outputs") or {}
    columns = OmegaConf.to_container(data.columns, resolve=True) if data.get("columns") is not None else {}
    if not _names(states) or not _names(inputs) or not isinstance(columns, Mapping):
        return
    mapped = {str(k): str(v) for k, v in columns.items()}
    observed, controls = list(data.observed or []), list(data.control_columns or [])
    names = [str(k) for k in outputs] if isinstance(outputs, Mapping) else []
    check_data_names(mapped, observed, controls, [*list(states or []), *names], list(inputs), names)


def _names(value: Any) -> bool:
    from omegaconf import ListConfig

    return isinstance(value, list | tuple | ListConfig) and all(isinstance(v, str) for v in value)


def main(argv: list[str] | None = None) -> None:
    """Console entry point (`mpsim`, `python -m mpsim`, `torchrun -m mpsim`).

    Sets the process up first (`mpsim.process.configure_process`: transparent huge pages for large CPU tensors,
    freed CPU memory kept for reuse), before torch is imported; importing mpsim itself changes nothing.
    """
    configure_process()
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(USAGE)
        return
    if argv[0] in ("-V", "--version"):
        from mpsim.version import __version__

        print(f"mpsim {__version__}")
        return
    command, rest = argv[0], argv[1:]
    if command not in COMMANDS:
        print(
            f"mpsim: unknown command {command!r}; choose one of {', '.join(COMMANDS)} (mpsim --help).", file=sys.stderr
        )
        sys.exit(2)
    if "--help" in rest or "-h" in rest:  # mpsim's own help for the command (Hydra's: --hydra-help)
        from mpsim.help import command_help

        print(command_help(command, CONF_DIR))
        return
    from mpsim.config import compose_command, register_schemas
    from mpsim.resume import with_resume

    try:
        if command == "train":
            rest = with_resume(rest)
        register_schemas()
        cfg = compose_command(command, rest, CONF_DIR)
        if cfg is not None:
            _check_writable(cfg, command)
            _check_spec_files(cfg)
            _check_data_names(cfg)
    except MpsimError as err:
        _fail(command, err)
    sys.argv = [f"mpsim {command}", *rest]
    COMMANDS[command]()


if __name__ == "__main__":
    main()
