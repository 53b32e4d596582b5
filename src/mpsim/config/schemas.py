"""The typed schemas of the fixed-shape config sections (data, trainer, mode, paths, eval and each command's
top-level keys), registered in Hydra's ConfigStore and named first in each primary config's defaults list: Hydra
rejects unknown keys and unconvertible values while composing."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, OmegaConf

from mpsim.config.records import run_name
from mpsim.diagnose.params import DiagnoseParams


@dataclass
class DataConf:
    path: str | None = None  # measured data: .npz, long or wide .csv, .mat; a glob ('rec/*.csv') reads several
    test_path: str | None = None  # recordings to test on (file or glob); data.path then trains (and validates)
    train_range: list[int] | None = None  # rows [start, stop) of every recording to train on, e.g. [0, 400]
    val_range: list[int] | None = None  # rows to validate on (default: data.path's end with test_path, else train)
    test_range: list[int] | None = None  # rows to test on, e.g. [400, 500]; the test records are kept whole
    edges: str | None = None  # edge-list CSV (src,dst) for CSV data; default <stem>_edges.csv
    graph: str | None = None  # "system": use system=<name>'s graph for a file without one
    control_columns: list[str] = field(default_factory=list)  # columns that are controls (the model's inputs)
    time_column: str | None = "t"  # wide CSV / .mat: the time column; null: none, samples data.dt apart
    columns: Any = None  # wide CSV / .mat: {model name: file column}
    observed: list[str] = field(default_factory=list)  # the states the file holds; others are estimated
    resample: float | None = None  # put every recording on one grid of this step (s)
    stride: int = 1  # keep every k-th sample
    segment: float | None = None  # cut recordings into segments of this many seconds
    input_hold: str = "linear"  # controls between samples: linear | zoh
    n_train: int = 200
    n_val: int = 50
    n_test: int = 50
    split: list[float] = field(default_factory=lambda: [0.7, 0.15, 0.15])  # file data: train/val/test shares
    dt: float | None = None  # sampling step; null = the system's default (a file without a time column: its step)
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
    init_samples: int | None = None  # measured data: samples that start each record's free run (null: as needed)
    freerun_substeps: int | None = 4  # RK4 steps per sample of a free run (null: the model's own solver)


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


def register_schemas() -> None:
    """Register each command's schema in Hydra's ConfigStore (`_<command>_schema`) and the `mpsim_run_name`
    resolver that names a run's folder."""
    if not OmegaConf.has_resolver("mpsim_run_name"):  # for hydra/output/mpsim.yaml's run directory
        OmegaConf.register_new_resolver("mpsim_run_name", run_name)
    cs = ConfigStore.instance()
    cs.store(name="_train_schema", node=TrainConf)
    cs.store(name="_eval_schema", node=EvalCmdConf)
    cs.store(name="_simulate_schema", node=SimulateConf)
    cs.store(name="_report_schema", node=ReportConf)
    cs.store(name="_bench_schema", node=BenchConf)
    cs.store(name="_diagnose_schema", node=DiagnoseConf)
