"""`mpsim <command> --help`: each command's own help, kept here as data (`HELP`).

A command's help says what it does, the keys a newcomer needs, the config groups it composes with their options
(read from the `conf/` directory when asked, so a new option file shows up without an edit here) and three
examples, and points to `--cfg job` (every key with its value) and `--hydra-help` (Hydra's own help). It imports
neither torch nor Hydra: it answers at once.
"""

from __future__ import annotations

import re
import textwrap
from dataclasses import dataclass
from pathlib import Path

import yaml

WIDTH = 100


@dataclass(frozen=True)
class CommandHelp:
    """One command's help text.

    Attributes:
        usage: the command line's shape after `mpsim <command>`.
        about: what the command does and what it writes (a paragraph).
        keys: (config key, its value's shape, what it does): the keys a newcomer needs. Every key is one of the
            composed config's (checked by tests/test_help.py), or a config group.
        examples: (command line, comment): three runs that work as written.
    """

    usage: str
    about: str
    keys: tuple[tuple[str, str, str], ...]
    examples: tuple[tuple[str, str], ...]


_DATA_KEYS = (
    ("data.path", "<file>", "measured trajectories (.npz, or a long .csv) instead of simulating system="),
    ("data.n_train", "<n>", "trajectories simulated for training (also data.n_val, data.n_test)"),
    ("data.horizon", "<steps>", "steps per trajectory (null: the system's own; also data.dt, data.seed)"),
)

HELP: dict[str, CommandHelp] = {
    "train": CommandHelp(
        usage="[key=value ...] [-m]",
        about=(
            "Train a model on trajectories of a system (simulated) or of a data file: from scratch (mode=scratch), "
            "from a checkpoint (init=<ckpt>: finetune), or evaluate a checkpoint without training (mode=zeroshot). "
            "Writes metrics.csv, summary.json, checkpoints/ and plots/ to outputs/train/<date>/<time>_<system>/ "
            "and exports the best model as checkpoints/<system>.ckpt. With -m, one job per combination of the "
            "comma-separated values (in parallel with hydra/launcher=joblib; an Optuna search with "
            "hydra/sweeper=optuna and key=interval(low,high)), ending with the table of the jobs."
        ),
        keys=(
            ("system", "<name>", "the dynamics to simulate and learn (group below)"),
            ("model", "<name>", "the model to train (group below)"),
            ("init", "<ckpt>", "start from this checkpoint (finetune): a path, or a name in paths.ckpt_dir"),
            ("mode", "scratch|finetune|zeroshot", "zeroshot evaluates init= without training"),
            ("resume", "true|<run dir>", "continue an interrupted run from its last.ckpt"),
            *_DATA_KEYS,
            ("trainer", "<name>", "training settings (group below): default, paper (4000 epochs), quick (3)"),
            ("trainer.max_epochs", "<n>", "epochs to train (also trainer.early_stop_patience, 0: never stop early)"),
            ("trainer.lr", "<rate>", "learning rate (also trainer.batch_size, trainer.clip_norm)"),
            ("trainer.progress", "true|false", "a progress bar on a terminal; else one line per trainer.log_every"),
            ("trainer.log_every", "<epochs>", "without a bar: one log line this many epochs apart (0: never)"),
            ("seed", "<n>", "weight initialisation and batch order (data.seed: the dataset)"),
            ("device", "auto|cpu|cuda", "where to compute"),
            ("objective", "<summary entry>", "the number a search (Optuna) minimises: best_val_error, test.rmse, ..."),
        ),
        examples=(
            ("mpsim train system=lorenz3", "train on 3 coupled Lorenz systems; exports checkpoints/lorenz3.ckpt"),
            ("mpsim train system=lorenz10 init=lorenz3.ckpt", "finetune that model on 10"),
            ("mpsim train -m system=lorenz10 data.n_train=50,100 init=lorenz3.ckpt,null", "a sweep: 4 jobs"),
        ),
    ),
    "eval": CommandHelp(
        usage="init=<ckpt> [key=value ...]",
        about=(
            "Evaluate a checkpoint on the test split of a system (simulated) or of a data file: rollout errors at "
            "the horizons in eval.horizons, plots. The model comes from the checkpoint; model.* overrides apply "
            "on top (model.zero_messages=true). Writes summary.json and plots/ to outputs/eval/<date>/<time>_<system>/."
        ),
        keys=(
            ("init", "<ckpt>", "the checkpoint to evaluate (required): a path, or a name in paths.ckpt_dir"),
            ("system", "<name>", "the system whose test split it is evaluated on (group below)"),
            ("data.path", "<file>", "evaluate on measured trajectories instead (.npz or .csv)"),
            ("data.n_test", "<n>", "test trajectories simulated (also data.horizon, data.seed)"),
            ("eval.horizons", "[1,10,...]", "steps at which the rollout RMSE is reported"),
            ("eval.save_predictions", "true|false", "also write test.npz and the model's rollout, test_model.npz"),
            ("device", "auto|cpu|cuda", "where to compute"),
        ),
        examples=(
            ("mpsim eval init=lorenz3.ckpt system=lorenz3", "the test error of the exported lorenz3 model"),
            ("mpsim eval init=lorenz3.ckpt system=lorenz10", "the same model on 10 coupled systems (zero-shot)"),
            ("mpsim eval init=lorenz3.ckpt data.path=my.csv data.split=[0,0,1]", "on all of a file's trajectories"),
        ),
    ),
    "simulate": CommandHelp(
        usage="[system=<name>] [key=value ...]",
        about=(
            "Simulate ground-truth trajectories of a system and export them (npz, long csv or both), with the "
            "model's rollout from the same initial states when init= is given. Writes <out>.npz/.csv and "
            "summary.json to outputs/simulate/<date>/<time>_<system>/."
        ),
        keys=(
            ("system", "<name>", "the system to simulate (group below)"),
            ("n", "<n>", "trajectories to simulate"),
            ("format", "npz|csv|both", "file format"),
            ("out", "<stem>", "file name (without suffix) inside the run directory"),
            ("init", "<ckpt>", "also export this model's rollout from the same initial states"),
            ("data.horizon", "<steps>", "steps per trajectory (also data.dt, data.burn_in)"),
            ("data.seed", "<n>", "initial states (seed= is for training and is refused here)"),
        ),
        examples=(
            ("mpsim simulate system=lorenz3 n=20", "20 trajectories as trajectories.npz"),
            ("mpsim simulate system=pendulum2 format=csv", "a long CSV (and its edge list) to read elsewhere"),
            ("mpsim simulate system=lorenz3 init=lorenz3.ckpt", "truth and the model's rollout side by side"),
        ),
    ),
    "diagnose": CommandHelp(
        usage="init=<ckpt> (system=<name> | data.path=<file>) [fix=true] [key=value ...]",
        about=(
            "Find the effect a trained model lacks in the data (damping, drag, forcing, a coupling, ...): fit "
            "candidate terms to its residual on held-in trajectories and name those that hold on held-out ones. "
            "With fix=true, add them, finetune and compare the held-out error before and after. Writes "
            "diagnosis.json, diagnosis.md and plots/ to outputs/diagnose/<date>/<time>_<system>/. Exit code: "
            "0 effects named, 10 nothing missing, 11 an unexplained structured residual."
        ),
        keys=(
            ("init", "<ckpt>", "the trained model to diagnose (required)"),
            ("system", "<name>", "the data's system (group below)"),
            ("data.path", "<file>", "or measured trajectories (.npz or .csv)"),
            ("fix", "true|false", "add the effects found, finetune from init=, compare"),
            ("diagnose.kinds", "[Bias,...]", "effect kinds searched (the library in mpsim.effects)"),
            ("diagnose.rounds", "<n>", "fix=true: at most this many add-finetune-diagnose rounds"),
            ("trainer.max_epochs", "<n>", "fix=true: epochs of each finetune (also trainer.lr)"),
        ),
        examples=(
            ("mpsim diagnose init=pendulum2.ckpt system=pendulum2", "what the model lacks, if anything"),
            ("mpsim diagnose init=pendulum2.ckpt data.path=measured.csv fix=true", "name it, add it, finetune"),
            ("mpsim diagnose init=lorenz3.ckpt system=lorenz3 'diagnose.kinds=[LinearDamping]'", "one kind only"),
        ),
    ),
    "report": CommandHelp(
        usage="runs='[<dir>, ...]' [key=value ...]",
        about=(
            "Tabulate finished runs: every summary.json under the given run or sweep folders, joined with the "
            "overrides each run was started with; runs that differ only by seed are averaged (mean ± std). Writes "
            "report.md and report.csv to outputs/report/<date>/<time>/; layout= draws one of the MP-NODE paper's "
            "tables or figures instead."
        ),
        keys=(
            ("runs", "'[<dir>, ...]'", "run or sweep folders (or globs) to scan"),
            ("group_by", "'[<key>, ...]'", "override keys to group by (default: every key that varies)"),
            ("columns", "'[<metric>, ...]'", "metric columns to show (default: all)"),
            ("target", "<error>|max_min", "adds epochs_to_target: the first epoch at or below this test error"),
            ("layout", "table2|table1|curves|message_size|messages", "a built-in paper layout"),
            ("title", "<text>", "the report's title"),
        ),
        examples=(
            ("mpsim report runs='[outputs/multirun]'", "every sweep job"),
            ("mpsim report runs='[outputs/multirun/train/2026-01-01/*]' target=0.1", "with epochs to reach 0.1"),
            ("mpsim report runs='[results/table2]' layout=table2", "the paper's Table 2"),
        ),
    ),
    "bench": CommandHelp(
        usage="bench=<suite> [key=value ...]",
        about=(
            "Measure performance ratios side by side in one process (the same machine, the same moment): rollout "
            "cost against graph size, S-MNN against odeint, epoch times at the paper's sizes, ... Writes a table "
            "and a plot to outputs/bench/<date>/<time>_<suite>/."
        ),
        keys=(
            ("bench", "<suite>", "what to measure (group below); its keys: mpsim bench bench=<suite> --cfg job"),
            ("device", "cpu|cuda|auto", "for the suites that take a device"),
            ("threads", "<n>", "torch CPU threads"),
        ),
        examples=(
            ("mpsim bench bench=mpnode", "MP-NODE rollout cost against N and batch size"),
            ("mpsim bench bench=smnn", "S-MNN's banded solve against odeint"),
            ("mpsim bench bench=mpnode bench.nodes=[2,10] bench.repeats=1", "a quick look"),
        ),
    ),
}


def config_groups(command: str, conf_dir: str | Path) -> list[tuple[str, str | None, list[str]]]:
    """The config groups `command` composes, as (group, its default option or None, every option), read from
    `conf/<command>.yaml`'s defaults list and the `conf/<group>/*.yaml` files."""
    conf = Path(conf_dir)
    spec = yaml.safe_load((conf / f"{command}.yaml").read_text()) or {}
    groups = []
    for entry in spec.get("defaults", []):
        if not isinstance(entry, dict):
            continue  # "_self_", the typed schema
        for group, default in entry.items():
            if " " in group or group.startswith(("hydra", "_")) or not (conf / group).is_dir():
                continue  # "override hydra/...": Hydra's own
            names = [p.stem for p in (conf / group).glob("*.yaml") if not p.stem.startswith("_")]
            options = sorted(names, key=lambda n: [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", n)])
            groups.append((group, default, options))
    return groups


def _columns(rows: list[tuple[str, str]], indent: int = 2) -> list[str]:
    """Two columns: the first padded to its widest entry, the second wrapped under itself."""
    width = min(max(len(left) for left, _ in rows), 44) + 2
    lines = []
    for left, right in rows:
        wrapped = textwrap.wrap(right, WIDTH - indent - width) or [""]
        head = f"{' ' * indent}{left:<{width}}"
        if len(left) >= width:  # too long to share its line
            lines.append(f"{' ' * indent}{left}")
            head = " " * (indent + width)
        lines.append(head + wrapped[0])
        lines += [" " * (indent + width) + w for w in wrapped[1:]]
    return lines


def command_help(command: str, conf_dir: str | Path) -> str:
    """`mpsim <command> --help`: what `command` does, its keys, its config groups, three examples."""
    h = HELP[command]
    usage = f"usage: mpsim {command} {h.usage} [--cfg job] [--hydra-help]"
    lines = [*textwrap.wrap(usage, WIDTH, subsequent_indent=" " * len(f"usage: mpsim {command} ")), ""]
    lines += textwrap.wrap(h.about, WIDTH) + ["", "keys (key=value on the command line):"]
    lines += _columns([(f"{key}={value}", text) for key, value, text in h.keys])
    groups = config_groups(command, conf_dir)
    if groups:
        where = f"config groups (group=option; each option is a file <conf>/<group>/<option>.yaml, conf = {conf_dir}):"
        lines += ["", *textwrap.wrap(where, WIDTH)]
        rows = []
        for group, default, options in groups:
            shown = [f"{o} (default)" if o == default else o for o in options]
            rows.append((group, ", ".join(shown) + ("" if default else "; none by default")))
        lines += _columns(rows)
    lines += ["", "examples:"]
    for example, comment in h.examples:
        lines += [f"  # {comment}", f"  {example}"]
    lines += [
        "",
        f"Every key with its value: mpsim {command} --cfg job (with your overrides: mpsim {command} <key=value ...> "
        f"--cfg job). Hydra's own help: mpsim {command} --hydra-help. All commands: mpsim --help.",
    ]
    return "\n".join(textwrap.fill(ln, WIDTH) if ln.startswith("Every key") else ln for ln in lines)
