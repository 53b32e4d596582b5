"""`mpsim <command> [hydra overrides]`: command dispatch only.

Hydra has no subcommands, so `main` pops the command word, rewrites `sys.argv` and calls that command's
`@hydra.main` wrapper, a thin shell around a plain `run_<command>(cfg) -> dict`. User-facing errors
(`MpsimError`) end with one message on stderr and a non-zero exit; anything else is a bug and keeps its
traceback.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from pathlib import Path

import hydra
import yaml
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from mpsim.config import register_schemas
from mpsim.errors import MpsimError

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

TRUE = {"true", "yes", "1", "on"}


def _guard(command: str, func: Callable[[DictConfig], dict], cfg: DictConfig) -> dict | None:
    """Run a command; turn user errors into one message and an exit code."""
    from mpsim.commands.common import hydra_overrides

    multirun = HydraConfig.initialized() and HydraConfig.get().mode.name == "MULTIRUN"
    try:
        result = func(cfg)
    except MpsimError as err:
        print(f"mpsim {command}: error: {err}", file=sys.stderr)
        sys.exit(err.exit_code)
    except KeyboardInterrupt:
        args = " ".join(a for a in hydra_overrides() if not a.startswith("resume="))
        print(f"\nmpsim {command}: interrupted. Completed epochs are saved in last.ckpt; continue with:\n"
              f"  mpsim {command} {args} resume=true", file=sys.stderr)
        sys.exit(130)
    if isinstance(result, dict) and result.get("status") == "diverged" and not multirun:
        print(f"mpsim {command}: training diverged; the best checkpoint so far was kept.", file=sys.stderr)
        sys.exit(3)
    return None if not multirun else {k: v for k, v in (result or {}).items() if isinstance(v, str | int | float)}


def _train() -> None:
    from mpsim.commands.train import run_train

    hydra.main(version_base="1.3", config_path="conf", config_name="train")(
        lambda cfg: _guard("train", run_train, cfg)
    )()


def _eval() -> None:
    from mpsim.commands.eval import run_eval

    hydra.main(version_base="1.3", config_path="conf", config_name="eval")(lambda cfg: _guard("eval", run_eval, cfg))()


def _simulate() -> None:
    from mpsim.commands.simulate import run_simulate

    hydra.main(version_base="1.3", config_path="conf", config_name="simulate")(
        lambda cfg: _guard("simulate", run_simulate, cfg)
    )()


def _report() -> None:
    from mpsim.commands.report import run_report

    hydra.main(version_base="1.3", config_path="conf", config_name="report")(
        lambda cfg: _guard("report", run_report, cfg)
    )()


def _diagnose() -> None:
    from mpsim.commands.diagnose import run_diagnose

    hydra.main(version_base="1.3", config_path="conf", config_name="diagnose")(
        lambda cfg: _guard("diagnose", run_diagnose, cfg)
    )()


def _bench() -> None:
    from mpsim.commands.bench import run_bench

    hydra.main(version_base="1.3", config_path="conf", config_name="bench")(
        lambda cfg: _guard("bench", run_bench, cfg)
    )()


COMMANDS: dict[str, Callable[[], None]] = {"train": _train, "eval": _eval, "simulate": _simulate, "report": _report, "bench": _bench, "diagnose": _diagnose}


def find_resumable(args: list[str], command: str = "train") -> Path | None:
    """The newest earlier run of `mpsim <command>` with the same overrides (ignoring `resume`) that has a
    `last.ckpt`, under `paths.output_root`."""
    key = sorted(a for a in args if not a.split("=", 1)[0].lstrip("+~").startswith(("resume", "hydra")))
    root = next((a.split("=", 1)[1] for a in args if a.startswith("paths.output_root=")), "outputs")
    found = []
    for overrides in Path(root).glob(f"{command}/*/*/.hydra/overrides.yaml"):
        run = overrides.parent.parent
        saved = yaml.safe_load(overrides.read_text()) or []
        saved = sorted(a for a in saved if not a.split("=", 1)[0].lstrip("+~").startswith(("resume", "hydra")))
        last = run / "checkpoints" / "last.ckpt"
        if saved == key and last.is_file():
            found.append((last.stat().st_mtime, run))
    return max(found)[1] if found else None


def _with_resume(args: list[str]) -> list[str]:
    """Point Hydra's run directory at the run that `resume=` continues."""
    values = [a.split("=", 1)[1] for a in args if a.startswith("resume=")]
    if not values or values[-1].lower() in {"false", "no", "0", "off", "null"}:
        return args
    if "-m" in args or "--multirun" in args:
        raise MpsimError("resume works for single runs; resume each sweep job with resume=<its run directory>.")
    value = values[-1]
    if value.lower() in TRUE:
        run = find_resumable(args)
        if run is None:
            shown = " ".join(a for a in args if not a.startswith("resume="))
            raise MpsimError(
                f"resume=true: no earlier run of `mpsim train {shown}` with a checkpoints/last.ckpt under "
                "outputs/train. Run it without resume=true first, or pass resume=<run directory>."
            )
    else:
        run = Path(value)
        if not (run / "checkpoints" / "last.ckpt").is_file():
            raise MpsimError(f"resume={value}: {run}/checkpoints/last.ckpt does not exist.")
    print(f"mpsim train: resuming {run}", file=sys.stderr)
    return [*args, f"hydra.run.dir={run.resolve()}"]


def main(argv: list[str] | None = None) -> None:
    """Console entry point."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(USAGE)
        return
    if argv[0] in ("-V", "--version"):
        from mpsim import __version__

        print(f"mpsim {__version__}")
        return
    command, rest = argv[0], argv[1:]
    if command not in COMMANDS:
        print(f"mpsim: unknown command {command!r}; choose one of {', '.join(COMMANDS)} (mpsim --help).",
              file=sys.stderr)
        sys.exit(2)
    try:
        if command == "train":
            rest = _with_resume(rest)
    except MpsimError as err:
        print(f"mpsim {command}: error: {err}", file=sys.stderr)
        sys.exit(2)
    register_schemas()
    sys.argv = [f"mpsim {command}", *rest]
    COMMANDS[command]()


if __name__ == "__main__":
    main()
