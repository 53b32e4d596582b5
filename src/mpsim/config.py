"""Config schemas and checks, used only by the command layer.

Two layers of checking make a typo or a wrong type fail at start with a clear message:

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
import types
import typing
from dataclasses import dataclass, field
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, OmegaConf

from mpsim.errors import ConfigError


@dataclass
class DataConf:
    path: str | None = None  # .npz or long .csv of measured trajectories (replaces simulation)
    edges: str | None = None  # edge-list CSV (src,dst) for CSV data; default <stem>_edges.csv
    graph: str | None = None  # "system": use system=<name>'s graph for a file without one
    control_columns: list[str] = field(default_factory=list)  # CSV columns that are controls
    n_train: int = 200
    n_val: int = 50
    n_test: int = 50
    split: list[float] = field(default_factory=lambda: [0.7, 0.15, 0.15])  # file data: train/val/test fractions
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
    _target_: str = "mpsim.training.Trainer"
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
    window: int | None = None
    eval_window: int | None = None


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


@dataclass
class TrainConf(CommonConf):
    trainer: TrainerConf = field(default_factory=TrainerConf)
    mode: ModeConf = field(default_factory=ModeConf)
    resume: Any = False  # true: continue the latest matching run; or a run directory
    export: bool = True  # copy the best checkpoint to <paths.ckpt_dir>/<system name>.ckpt


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


@dataclass
class DiagnoseParams:
    kinds: list[str] = field(default_factory=lambda: ["Bias", "LinearDamping", "QuadraticDrag", "CubicStiffness",
                                                      "DiffusiveCoupling", "SineCoupling", "PeriodicForcing",
                                                      "DelayedFeedback"])
    delays: list[float] | None = None
    n_boot: int = 100
    min_gain: float = 0.05
    null_factor: float = 3.0
    min_inclusion: float = 0.8
    vpt_threshold: float = 0.3
    fix_lr_factor: float = 0.1
    rounds: int = 3


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


def register_schemas() -> None:
    cs = ConfigStore.instance()
    cs.store(name="_train_schema", node=TrainConf)
    cs.store(name="_eval_schema", node=EvalCmdConf)
    cs.store(name="_simulate_schema", node=SimulateConf)
    cs.store(name="_report_schema", node=ReportConf)
    cs.store(name="_bench_schema", node=BenchConf)
    cs.store(name="_diagnose_schema", node=DiagnoseConf)


# ---- _target_ nodes ----------------------------------------------------------------------------------------
def _import(path: str, where: str) -> Any:
    module, _, name = path.rpartition(".")
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError, ValueError):
        raise ConfigError(f"{where}._target_: cannot import {path!r}. Check the spelling or install its package.") from None


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
