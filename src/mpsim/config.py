"""Config schemas and checks, used only by the command layer.

Before Hydra starts a run, `compose_command` composes the command line exactly as the run will (no torch
import, no run directory), turns Hydra's composition errors into one line with a did-you-mean (Hydra's own
advice, "To append to your config use +key", is the wrong fix for a typo) and checks value ranges
(`validate_values`). Two layers of checking make a typo or a wrong type fail at start with a clear message:

1. Typed structured-config schemas (dataclasses below, registered in Hydra's ConfigStore and named first in
   each primary config's defaults list) cover the fixed-shape parts: data, trainer, mode, paths, eval and the
   top-level keys. Hydra rejects unknown keys and unconvertible values while composing.
2. Nodes with a `_target_` (system, model, solver, ...) differ per target, so they are checked against the
   target's own signature (`check_targets`): unknown keys get a did-you-mean, values are checked against the
   parameter annotations. A user who points a group at their own class gets the same checks for free.
"""

from __future__ import annotations

import difflib
import importlib
import inspect
import math
import re
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import yaml
from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, ListConfig, OmegaConf

from mpsim.diagnose.params import DiagnoseParams
from mpsim.errors import ConfigError, DataError
from mpsim.process import DEVICE
from mpsim.safeload import RECORD_BYTES, load_yaml


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


@dataclass
class DataConf:
    path: str | None = None  # .npz or long .csv of measured trajectories (replaces simulation)
    edges: str | None = None  # edge-list CSV (src,dst) for CSV data; default <stem>_edges.csv
    graph: str | None = None  # "system": use system=<name>'s graph for a file without one
    control_columns: list[str] = field(default_factory=list)  # CSV columns that are controls
    n_train: int = 200
    n_val: int = 50
    n_test: int = 50
    split: list[float] = field(default_factory=lambda: [0.7, 0.15, 0.15])  # file data: train/val/test shares
    dt: float | None = None  # sampling step; null = the system's default
    horizon: int | None = None  # steps per trajectory; null = the system's default
    burn_in: int = 0  # steps simulated and discarded before each record (e.g. to start on an attractor)
    seed: int = 0  # dataset seed (initial states), separate from the training seed
    noise_std: float = 0.0  # Gaussian noise on training states, in units of each feature's std
    cache: bool = True
    gt_rtol: float = 1.0e-8  # ground-truth solver tolerances (float64, dopri5)
    gt_atol: float = 1.0e-10


@dataclass
class TrainerConf:
    _target_: str = "mpsim.training.trainer.Trainer"
    max_epochs: int = 100
    batch_size: int = 32
    lr: float = 3.0e-3
    weight_decay: float = 0.0
    clip_norm: float = 500.0
    loss: str = "huber"
    huber_delta: float = 1.0
    plateau_patience: int = 10
    plateau_factor: float = 0.5
    min_lr: float = 1.0e-6
    early_stop_patience: int = 30
    eval_batch_size: int = 512
    progress: bool = True
    log_every_s: float = 300.0
    window: int | None = None
    eval_window: int | None = None
    optimizer: str = "adam"  # adam | lbfgs (white-box models: lr 1, full batches; see trainer=whitebox)
    log_every: int = 10  # without a bar (progress=false, or no terminal): one log line every this many epochs


@dataclass
class ModeConf:
    name: str = "scratch"
    refit_normalisation: bool = False


@dataclass
class PathsConf:
    output_root: str = "outputs"
    ckpt_dir: str = "checkpoints"
    cache_dir: str = "outputs/.cache"


@dataclass
class EvalConf:
    horizons: list[int] = field(default_factory=lambda: [1, 10, 25, 50])  # steps at which RMSE is reported
    n_plot: int = 2  # test trajectories drawn in the trajectory plot
    plots: bool = True
    save_predictions: bool = False  # write the test split and the model's rollout of it (test.npz, test_model.npz)


@dataclass
class CommonConf:
    task: str = MISSING
    system: Any = MISSING
    model: Any = MISSING
    solver: Any = MISSING
    data: DataConf = field(default_factory=DataConf)
    paths: PathsConf = field(default_factory=PathsConf)
    eval: EvalConf = field(default_factory=EvalConf)
    seed: int = 0
    init: str | None = None
    device: str = "auto"  # auto | cpu | cuda | cuda:1 ...
    dtype: str = "float32"  # model precision: float32 | float64
    threads: int | None = 1  # torch CPU threads (null: torch's default, or cores / jobs under joblib)
    memory_check: bool = True  # refuse a simulation/dataset/training step whose memory estimate does not fit
    overwrite: bool = False  # a run folder that holds a run: move its files to <folder>/backup-<time>/, then write


@dataclass
class TrainConf(CommonConf):
    trainer: TrainerConf = field(default_factory=TrainerConf)
    mode: ModeConf = field(default_factory=ModeConf)
    resume: Any = False  # true: continue the latest matching run; or a run directory
    export: bool = True  # copy the best checkpoint to <paths.ckpt_dir>/<system name>.ckpt
    objective: str = "best_val_error"  # summary entry returned to Hydra sweepers (Optuna minimises it)
    logger: Any = None  # {name: _target_ node}: conf/logger (csv, tensorboard, mlflow, several at once)


@dataclass
class EvalCmdConf(CommonConf):
    pass


@dataclass
class SimulateConf(CommonConf):
    n: int = 8  # trajectories to simulate
    format: str = "npz"  # npz | csv | both
    out: str = "trajectories"  # file stem inside the run directory


@dataclass
class ReportConf:
    task: str = "report"
    runs: list[str] = field(default_factory=lambda: ["outputs"])  # run/sweep directories or globs to scan
    group_by: list[str] = field(default_factory=list)  # override keys to group by (default: all that vary)
    paths: PathsConf = field(default_factory=PathsConf)
    title: str = "mpsim report"
    target: Any = None  # test error for `epochs_to_target`: a number, or max_min (the level every run reached)
    columns: list[str] = field(default_factory=list)  # metrics to show (default: all)
    layout: str | None = None  # table2 | table1 | curves | message_size: a built-in MP-NODE paper layout
    overwrite: bool = False  # a run folder that holds a run: move its files to <folder>/backup-<time>/, then write


@dataclass
class DiagnoseConf(CommonConf):
    trainer: TrainerConf = field(default_factory=TrainerConf)
    fix: bool = False
    diagnose: DiagnoseParams = field(default_factory=DiagnoseParams)


@dataclass
class BenchConf:
    task: str = "bench"
    bench: Any = MISSING
    paths: PathsConf = field(default_factory=PathsConf)
    threads: int | None = 1
    device: str = "cpu"  # cpu | cuda | auto: passed to suites that take a device
    overwrite: bool = False  # a run folder that holds a run: move its files to <folder>/backup-<time>/, then write


def read_overrides_file(run: str | Path) -> list[str] | None:
    """A run's `.hydra/overrides.yaml` (the overrides it was started with) as a list of `key=value` strings, or
    None where the run kept none. A file that is not a YAML list of overrides is a DataError that names it: the
    record is read as data only, and a damaged one is never taken as "no overrides"."""
    path = Path(run) / ".hydra" / "overrides.yaml"
    if not path.exists():
        return None
    fix = "Restore it (a YAML list of key=value overrides, as Hydra wrote it) or move the run away"
    try:  # data only (a python tag is an error, never run), bounded in size, nesting and aliases
        saved = load_yaml(path, RECORD_BYTES, str(path), fix)
    except UnicodeDecodeError as err:
        raise DataError(f"{path} is not valid YAML (not UTF-8 text: {err.reason}). {fix}.") from None
    except OSError as err:
        raise DataError(f"{path} could not be read ({err.strerror or err}). {fix}.") from None
    except yaml.YAMLError as err:
        raise DataError(f"{path} is not valid YAML ({str(err).splitlines()[0]}). {fix}.") from None
    if saved is None:
        return []
    if not isinstance(saved, list) or not all(isinstance(o, str | int | float | bool) for o in saved):
        got = type(saved).__name__ if not isinstance(saved, list) else "a list with nested values"
        raise DataError(f"{path} must be a list of key=value overrides; got {got}. {fix}.")
    return [str(o) for o in saved]


def file_stem(path: str | Path) -> str:
    """A file's name without its suffix, reduced to ``[A-Za-z0-9_.-]`` (a name for runs and systems); may be ""."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", Path(str(path)).stem).strip("._")


def run_name(system_choice: str, data_path: Any = None) -> str:
    """The suffix of a run's directory: the data file's name when the run reads one (`data.path`), else the
    system's (`outputs/train/<date>/<time>_<this>`)."""
    return (file_stem(data_path) if data_path else "") or system_choice


def register_schemas() -> None:
    if not OmegaConf.has_resolver("mpsim_run_name"):  # for hydra/output/mpsim.yaml's run directory
        OmegaConf.register_new_resolver("mpsim_run_name", run_name)
    cs = ConfigStore.instance()
    cs.store(name="_train_schema", node=TrainConf)
    cs.store(name="_eval_schema", node=EvalCmdConf)
    cs.store(name="_simulate_schema", node=SimulateConf)
    cs.store(name="_report_schema", node=ReportConf)
    cs.store(name="_bench_schema", node=BenchConf)
    cs.store(name="_diagnose_schema", node=DiagnoseConf)


# ---- _target_ nodes ----------------------------------------------------------------------------------------
def plain_dict(node: DictConfig) -> dict[str, Any]:
    """A config section as plain, resolved Python data (`OmegaConf.to_container` is typed for any node)."""
    out = OmegaConf.to_container(node, resolve=True)
    assert isinstance(out, dict)  # a DictConfig converts to a dict
    return cast(dict[str, Any], out)  # OmegaConf types the keys as any primitive; mpsim's sections use names


def _import(path: str, where: str) -> Any:
    module, _, name = path.rpartition(".")
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError, ValueError):
        raise ConfigError(
            f"{where}._target_: cannot import {path!r}. Check the spelling or install its package."
        ) from None


def _type_ok(value: Any, annotation: Any) -> bool:
    """Whether `value` (a plain config value) fits `annotation` (conservative: unknown annotations pass)."""
    if annotation is inspect.Parameter.empty or annotation is Any:
        return True
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        return any(_type_ok(value, a) for a in typing.get_args(annotation))
    if annotation is type(None):
        return value is None
    if annotation is bool:
        return isinstance(value, bool)
    if annotation is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if annotation is float:
        return isinstance(value, int | float) and not isinstance(value, bool)
    if annotation is str:
        return isinstance(value, str)
    if origin in (list, tuple, typing.Sequence) or annotation in (list, tuple):
        return isinstance(value, list | tuple)
    if origin is dict or annotation is dict:
        return isinstance(value, dict)
    return True


def _describe(annotation: Any) -> str:
    return getattr(annotation, "__name__", None) or str(annotation).replace("typing.", "")


def check_target_node(node: Any, where: str) -> None:
    """Check one `_target_` node's keys and values against its target's signature.

    Raises:
        ConfigError: unknown key (with suggestions) or a value of the wrong type.
    """
    if not isinstance(node, dict) or "_target_" not in node:
        return
    target = _import(node["_target_"], where)
    func = target.__init__ if inspect.isclass(target) else target
    try:
        sig = inspect.signature(func)
        hints = typing.get_type_hints(func)
    except (TypeError, ValueError, NameError):
        return
    params = {k: p for k, p in sig.parameters.items() if k != "self"}
    if any(p.kind is p.VAR_KEYWORD for p in params.values()):
        return
    for key, value in node.items():
        if key.startswith("_"):
            continue
        if key not in params:
            close = difflib.get_close_matches(key, list(params), n=3)
            hint = f" Did you mean {' or '.join(close)}?" if close else ""
            raise ConfigError(
                f"{where}.{key} is not a parameter of {node['_target_']}.{hint} "
                f"Valid keys: {', '.join(k for k in params if k not in ('effects',))}."
            )
        annotation = hints.get(key, params[key].annotation)
        if not _type_ok(value, annotation):
            raise ConfigError(
                f"{where}.{key}={value!r} has the wrong type: {node['_target_']} expects {_describe(annotation)}."
            )


def check_targets(cfg: DictConfig, keys: tuple[str, ...] = ("system", "model", "solver")) -> None:
    """Check every listed `_target_` node of a composed config (see `check_target_node`)."""
    for key in keys:
        if key in cfg and cfg[key] is not None:
            check_target_node(OmegaConf.to_container(cfg[key], resolve=True), key)


# ---- values ------------------------------------------------------------------------------------------------
_FINITE_GROUPS = ("system", "model", "solver", "trainer", "data", "eval")


def _check(ok: bool, message: str) -> None:
    if not ok:
        raise ConfigError(message)


def _nonfinite(node: Any, where: str, allow_inf: bool) -> str | None:
    """The first key under `node` holding NaN (or ±inf unless `allow_inf`), as `key=value`."""
    if isinstance(node, dict):
        for key, value in node.items():
            found = _nonfinite(value, f"{where}.{key}", allow_inf)
            if found:
                return found
    elif isinstance(node, list | tuple):
        for i, value in enumerate(node):
            found = _nonfinite(value, f"{where}[{i}]", allow_inf)
            if found:
                return found
    elif isinstance(node, float) and (math.isnan(node) or (math.isinf(node) and not allow_inf)):
        return f"{where}={node}"
    return None


def validate_values(cfg: DictConfig) -> None:
    """Check the values every command relies on (ranges, choices, finiteness) without importing torch.

    Raises:
        ConfigError: the first value that is out of range, naming the key, the rule and the fix.
    """
    if "device" in cfg:
        _check(
            bool(DEVICE.fullmatch(str(cfg.device))),
            f"device={cfg.device} is not supported; choose auto, cpu, cuda, cuda:<index> or mps.",
        )
    if cfg.get("threads") is not None:
        _check(
            cfg.threads >= 1,
            f"threads={cfg.threads}: give a number of CPU threads >= 1, or threads=null for torch's default.",
        )
    for group in _FINITE_GROUPS:
        if cfg.get(group) is None:
            continue
        try:
            node = OmegaConf.to_container(cfg[group], resolve=True)
        except Exception:  # noqa: BLE001 - unresolvable interpolations are reported where they are used
            continue
        bad = _nonfinite(node, group, allow_inf=group in ("trainer", "model", "solver"))
        _check(bad is None, f"{bad} is not a finite number; give a finite value for {str(bad).split('=')[0]}.")
    data = cfg.get("data")
    if data is not None:
        _check(
            data.noise_std >= 0,
            f"data.noise_std={data.noise_std}: noise is a standard deviation (in units of each "
            "feature's std); give a value >= 0 (0: no noise).",
        )
        for key in ("n_train", "n_val", "n_test"):
            _check(data[key] >= 1, f"data.{key}={data[key]}: each split needs at least 1 trajectory.")
        _check(data.burn_in >= 0, f"data.burn_in={data.burn_in}: give a number of steps >= 0.")
        _check(data.dt is None or data.dt > 0, f"data.dt={data.dt}: the sampling step must be > 0 (or null).")
        _check(data.horizon is None or data.horizon >= 1, f"data.horizon={data.horizon}: give >= 1 step (or null).")
        _check(data.gt_rtol > 0 and data.gt_atol > 0, "data.gt_rtol and data.gt_atol must be > 0.")
    ev = cfg.get("eval")
    if ev is not None:
        bad_h = [h for h in ev.horizons if h < 1]
        _check(not bad_h, f"eval.horizons={list(ev.horizons)}: horizons are numbers of steps >= 1; remove {bad_h}.")
    trainer = cfg.get("trainer")
    if trainer is not None:
        _validate_trainer(trainer)
    if "n" in cfg and cfg.get("task") == "simulate":
        _check(cfg.n >= 1, f"n={cfg.n}: simulate at least 1 trajectory.")


def _validate_trainer(t: DictConfig) -> None:
    rules = [
        ("max_epochs", lambda v: v >= 0, ">= 0"),
        ("batch_size", lambda v: v >= 1, ">= 1"),
        ("eval_batch_size", lambda v: v >= 1, ">= 1"),
        ("lr", lambda v: 0 < v < math.inf, "> 0 and finite"),
        ("weight_decay", lambda v: v >= 0, ">= 0"),
        ("clip_norm", lambda v: v >= 0, ">= 0 (0: no clipping)"),
        ("huber_delta", lambda v: v > 0, "> 0"),
        ("plateau_patience", lambda v: v >= 0, ">= 0"),
        ("plateau_factor", lambda v: 0 < v < 1, "between 0 and 1"),
        ("min_lr", lambda v: v >= 0, ">= 0"),
        ("early_stop_patience", lambda v: v >= 0, ">= 0 (0: never stop early)"),
        ("log_every_s", lambda v: v >= 0, ">= 0 seconds (0: never)"),
        ("log_every", lambda v: v >= 0, ">= 0 epochs (0: never)"),
        ("window", lambda v: v is None or v >= 1, ">= 1 step, or null"),
        ("eval_window", lambda v: v is None or v >= 1, ">= 1 step, or null"),
    ]
    for key, ok, rule in rules:
        if key in t and isinstance(t[key], int | float | type(None)) and not ok(t[key]):
            raise ConfigError(f"trainer.{key}={t[key]}: must be {rule}.")


# ---- composing the command line (before Hydra starts a run) -------------------------------------------------
_FLAGS_WITHOUT_VALUE = ("-m", "--multirun")


MAX_SWEEP_CHECKS = 64


def _sweep_variants(args: list[str]) -> list[list[str]] | None:
    """Override lists that together use every value of every sweep at least once: the first values, then each
    other value of one sweep with the others at their first (None if the sweeps cannot be expanded here)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import IntervalSweep

    parsed = OverridesParser.create().parse_overrides(args)
    values: list[list[str]] = []
    for item in parsed:
        sweep = item.value()
        if isinstance(sweep, IntervalSweep):  # an Optuna search space: its two ends stand for the values it may take
            ends = [int(v) if v is not None and float(v).is_integer() else v for v in (sweep.start, sweep.end)]
            values.append([f"{item.get_key_element()}={v}" for v in ends])
        elif item.is_sweep_override():
            try:
                values.append([f"{item.get_key_element()}={v}" for v in item.sweep_string_iterator()])
            except Exception:  # noqa: BLE001 - glob() and friends need Hydra's config loader
                return None
        else:
            assert item.input_line is not None  # parse_overrides sets it on every override it returns
            values.append([item.input_line])
    first = [v[0] for v in values]
    variants = [first]
    for i, options in enumerate(values):
        for option in options[1:]:
            variants.append([*first[:i], option, *first[i + 1 :]])
    return variants[:MAX_SWEEP_CHECKS]


def _quote_hint(overrides: list[str]) -> str:
    """Advice for the override Hydra could not parse when its value holds a call or an `=`: an inline equation
    `omega: -g*sin(theta)` (Hydra reads `sin(...)` as one of its own functions) or a nested override
    `overrides: [system=lorenz3]`; quoted inside the override, either is a plain string."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    for arg in overrides:
        key, _, value = arg.partition("=")
        if "(" not in value and "=" not in value:
            continue
        try:
            parser.parse_override(arg)
        except Exception:  # noqa: BLE001 - Hydra raises several kinds for one unparsable override
            if "(" in value and not key.lstrip("+~").endswith(("equations", "spec")):
                shown = value.replace('"', "'")
                return f""". In {key}=..., quote the value inside the single quotes: '{key}="{shown}"'"""
            if "(" in value:
                return (
                    f". In {key}=..., quote every expression that calls a function, inside the single quotes: "
                    f"'{key}={{omega: \"-g*sin(theta)\"}}' (or write it in a spec file)"
                )
            return f'. In {key}=..., quote every item that holds "=", inside the single quotes: [..., "system=lorenz3"]'
    return ""


def compose_command(command: str, args: list[str], config_dir: str) -> DictConfig | None:
    """Compose `command`'s config from its command-line `args` exactly as the run will, and check it.

    Runs before Hydra creates a run directory, without importing torch, so a typo or a bad value answers at
    once and leaves nothing behind. Returns None when the arguments hold options this check leaves to Hydra
    (``--cfg``, ``--help``, ``--config-dir``, ...).

    Raises:
        ConfigError: unknown key (with a did-you-mean instead of Hydra's "+key" advice), unknown option of a
            config group, a value of the wrong type, or a value out of range (`validate_values`).
    """
    from hydra import compose, initialize_config_dir
    from hydra.errors import OverrideParseException

    if any(a.startswith("-") and a not in _FLAGS_WITHOUT_VALUE for a in args):
        return None
    overrides = [a for a in args if a not in _FLAGS_WITHOUT_VALUE]
    try:
        variants = _sweep_variants(overrides)
    except OverrideParseException as err:
        raise ConfigError(f"cannot parse the command line: {_one_line(err)}{_quote_hint(overrides)}") from None
    if variants is None:
        return None

    def _compose(items: list[str], hydra: bool = False) -> DictConfig:
        with initialize_config_dir(config_dir=config_dir, version_base="1.3", job_name=command):
            return compose(config_name=command, overrides=items, return_hydra_config=hydra)

    first = _compose_one(variants[0], _compose, config_dir)
    if any("sweeper" in a or a.startswith("hparams_search") or "interval(" in a for a in overrides):
        validate_search(_compose(variants[0], hydra=True).hydra.sweeper, overrides, first)
    validate_values(first)
    for items in variants[1:]:
        validate_values(_compose_one(items, _compose, config_dir))
    return first


def validate_search(sweeper: DictConfig, overrides: list[str], cfg: DictConfig) -> None:
    """Check an Optuna search (hparams_search=... or hydra/sweeper=optuna) before its first trial: the trial
    count, the direction, and every search space (`hydra.sweeper.params` and `key=interval(...)` /
    `choice(...)` on the command line) as Optuna will read it, so a typo is one message instead of a traceback after the study was created. `cfg`
    (the composed run config) tells which keys hold whole numbers: their intervals need the `int` tag."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import IntervalSweep

    intervals = [a for a in overrides if "interval(" in a and not a.startswith("hydra.")]
    if "optuna" not in str(sweeper.get("_target_", "")).lower():
        if intervals:
            key = intervals[0].split("=", 1)[0]
            raise ConfigError(
                f"{intervals[0]}: an interval is a search space, for an Optuna search (hparams_search=<file> or -m "
                f"hydra/sweeper=optuna); a -m sweep takes a list of values, e.g. {key}=1e-3,3e-3,1e-2."
            )
        return
    for key in ("n_trials", "n_jobs"):
        value = sweeper.get(key)
        if not isinstance(value, int) or isinstance(value, bool) or value < 1:
            raise ConfigError(f"hydra.sweeper.{key}={value}: must be a whole number >= 1.")
    _check_direction(sweeper.get("direction"))
    parser = OverridesParser.create()
    spaces = [(f"hydra.sweeper.params.{k}", f"{k}={v}") for k, v in (sweeper.get("params") or {}).items()]
    spaces += [(a.split("=", 1)[0], a) for a in intervals]
    for where, text in spaces:
        try:
            sweep = parser.parse_override(text).value()
        except Exception as err:  # noqa: BLE001 - Hydra raises several kinds for one unparsable override
            raise ConfigError(
                f"{where}: cannot read the search space {text.split('=', 1)[1]!r}: {_one_line(err)}"
            ) from None
        if isinstance(sweep, IntervalSweep):
            low, high = sweep.start, sweep.end
            if low is None or high is None or not low <= high:
                raise ConfigError(f"{where}=interval({low}, {high}): the low end must not exceed the high end.")
            key = text.split("=", 1)[0]
            if isinstance(OmegaConf.select(cfg, key), int):  # Hydra reads interval ends as floats: always fractions
                raise ConfigError(
                    f"{where}=interval({low:g}, {high:g}): {key} is a whole number, and Optuna draws fractions "
                    f"from an interval; write range({low:g}, {high:g}) (whole numbers, both ends included) or "
                    "choice(...)."
                )
            if "log" in sweep.tags and low <= 0:
                raise ConfigError(
                    f"{where}=tag(log, interval({low}, {high})): a log-scale interval needs a low end > 0, "
                    f"e.g. interval({high / 100:g}, {high:g})."
                )


def _check_direction(direction: Any) -> None:
    """`hydra.sweeper.direction` as the Optuna sweeper reads it: its own default, the enum `Direction.minimize`
    (`hydra/sweeper=optuna`), the string `minimize` or `maximize` (a yaml file or an override), or a list of them,
    one per objective. mpsim returns one objective (`objective=`), so a list holds one direction."""
    items = list(direction) if isinstance(direction, ListConfig | list | tuple) else [direction]
    names = [getattr(d, "name", d) for d in items]  # an Enum member -> its name
    if not names or any(n not in ("minimize", "maximize") for n in names):
        raise ConfigError(
            f"hydra.sweeper.direction={direction}: must be minimize or maximize (mpsim's objective "
            "is an error: minimize)."
        )
    if len(names) > 1:
        raise ConfigError(
            f"hydra.sweeper.direction={direction}: one direction per objective, and mpsim train returns one "
            "objective (objective=<summary entry>); give one: hydra.sweeper.direction=minimize."
        )


def _compose_one(firsts: list[str], _compose: Any, config_dir: str) -> DictConfig:
    """Compose one override list, turning Hydra's composition errors into `ConfigError`."""
    from hydra.errors import ConfigCompositionException, HydraException, MissingConfigException

    try:
        return _compose(firsts)
    except MissingConfigException as err:
        raise ConfigError(_one_line(err)) from None
    except ConfigCompositionException as err:
        text = str(err)
        match = re.match(r"Could not override '([^']+)'", text)
        if match:
            raise ConfigError(
                _unknown_key(
                    match.group(1), [a for a in firsts if not _is_key(a, match.group(1))], _compose, config_dir
                )
            ) from None
        cause = f": {_one_line(err.__cause__)}" if err.__cause__ is not None else ""
        raise ConfigError(f"{_one_line(err)}{cause}") from None
    except HydraException as err:
        raise ConfigError(_one_line(err)) from None


def _is_key(arg: str, key: str) -> bool:
    return arg.split("=", 1)[0].lstrip("+~") == key


def _one_line(err: BaseException) -> str:
    """An exception's message on one line (Hydra's option listings joined with commas)."""
    lines = [ln.strip() for ln in str(err).splitlines() if ln.strip()]
    lines = [ln for ln in lines if not ln.startswith(("full_key:", "object_type=", "reference_type=", "To append"))]
    if not lines:
        return type(err).__name__
    head, rest = lines[0], lines[1:]
    if rest and rest[0].startswith("Available options"):
        options = [ln for ln in rest[1:] if not ln.startswith(("Config search path", "provider="))]
        return f"{head.rstrip('.')}. {rest[0]} {', '.join(options)}."
    return " ".join([head, *rest[:2]])


#: top-level names users reach for, other tools' words for a key mpsim has
_SYNONYMS = {"ckpt": "init", "checkpoint": "init", "load": "init", "weights": "init", "epochs": "trainer.max_epochs"}


def _unknown_key(key: str, others: list[str], compose_fn: Any, config_dir: str) -> str:
    """Message for `key=...` naming no key of the composed config: the closest keys, or how to add a parameter
    that the target class takes but its config file does not list."""
    parent, _, leaf = key.rpartition(".")
    if key.startswith("hydra.sweeper.params."):  # its keys hold dots: an override cannot reach them
        name = key.removeprefix("hydra.sweeper.params.")
        return (
            f"{key}: a search space is given on the key itself, '{name}=interval(low, high)', "
            f"'{name}=tag(log, interval(low, high))' or '{name}=choice(a, b)' (with hparams_search=...), or in a "
            "copy of conf/hparams_search/*.yaml."
        )
    try:
        base = compose_fn(others, hydra=True) if key.startswith("hydra.") else compose_fn(others)
    except Exception:  # noqa: BLE001
        return f"{key} is not a config key. Check its spelling (mpsim <command> --cfg job lists every key)."
    node = OmegaConf.select(base, parent) if parent else base
    if not isinstance(node, DictConfig):
        parts, here = key.split("."), base
        for depth, part in enumerate(parts[:-1]):
            if not isinstance(here, DictConfig) or part not in here:
                options = [str(k) for k in here.keys()] if isinstance(here, DictConfig) else []
                close = difflib.get_close_matches(part, options, n=3, cutoff=0.6)
                prefix = ".".join(parts[:depth])
                name = f"{prefix}.{part}" if prefix else part
                hint = (
                    f" Did you mean {' or '.join((prefix + '.' if prefix else '') + c for c in close)}?"
                    if close
                    else ""
                )
                return f"{key}: {name} is not a config section.{hint} (mpsim <command> --cfg job lists every key.)"
            here = here[part]
        return f"{key}: {parent} is not a config section (mpsim <command> --cfg job lists every key)."
    keys = [str(k) for k in node.keys()]
    where = f"{parent}." if parent else ""
    if not parent:  # a top-level name may also be a config group
        keys += [p.name for p in Path(config_dir).iterdir() if p.is_dir() and not p.name.startswith("_")]
    close = difflib.get_close_matches(leaf, keys, n=3, cutoff=0.6)
    if not parent and leaf in _SYNONYMS and _SYNONYMS[leaf].split(".")[0] in keys:
        close = [_SYNONYMS[leaf]]
    if close:
        return (
            f"{key} is not a config key. Did you mean {' or '.join(where + c for c in close)}? "
            f"Keys of {parent or 'the config'}: {', '.join(sorted(set(k for k in keys if not k.startswith('_'))))}."
        )
    target = node.get("_target_") if parent else None
    if isinstance(target, str):
        params: Mapping[str, inspect.Parameter]
        try:
            obj = _import(target, parent)
            params = inspect.signature(obj.__init__ if inspect.isclass(obj) else obj).parameters
        except (ConfigError, TypeError, ValueError):
            params = {}
        if leaf in params:
            return (
                f"{key} is a parameter of {target} that {parent}'s config file does not list; add it with "
                f"+{key}=<value>."
            )
        close = difflib.get_close_matches(leaf, [p for p in params if p != "self"], n=3, cutoff=0.6)
        if close:
            return f"{key} is not a parameter of {target}. Did you mean {' or '.join(where + c for c in close)}?"
    listing = ", ".join(sorted({k for k in keys if not k.startswith("_")}))  # a group may also be a key
    return f"{key} is not a config key; {parent or 'the config'} has: {listing}."
