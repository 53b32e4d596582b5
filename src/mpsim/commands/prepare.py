"""The composition root: `prepare(cfg, command) -> Job`, the one function below the `run_<command>` wrappers that
reads the config. It checks the composed config, sets up where and how the command runs, finds the starting
checkpoint (or the run being resumed), builds the system, the solver and the model, and loads the data through
the pipeline (`mpsim.data.pipeline`) — in the order that writes nothing before a bad input is found: the model
is checked against the system before any data is simulated into the cache. Everything it hands on is a plain
value or an object built from one.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, open_dict

from mpsim.commands.building import Shape, build, build_model_for, model_config
from mpsim.commands.guards import check_simulation_memory, fit_horizons
from mpsim.commands.init_ckpt import load_init
from mpsim.commands.resumed import load_resumed
from mpsim.commands.runtime import Runtime, given, make_runtime, resolve_path, start_directory
from mpsim.config import check_targets, file_stem, plain_dict, validate_values
from mpsim.data.dataset import SPLITS, Splits, fit_normalisation
from mpsim.data.pipeline import DataOptions, load_splits
from mpsim.errors import ConfigError
from mpsim.models.base import Model
from mpsim.solvers.odeint import ODESolver
from mpsim.spec import load_spec_file
from mpsim.systems.base import System
from mpsim.training import distributed
from mpsim.training.distributed import SINGLE, DistContext

MODES = ("scratch", "finetune", "zeroshot")


@dataclass(frozen=True)
class Job:
    """What a command computes with, built once from its config by `prepare`.

    Attributes:
        runtime: device, dtype, start and run directories, overrides, memory check.
        mode: `mpsim train`'s scratch | finetune | zeroshot; the command's name for the others.
        seed: the training seed (weights, batch order; torch is seeded with it).
        system: the ground truth (None for a data file without `data.graph=system`).
        checkpoint: the `init=` checkpoint, or None.
        resumed: the `last.ckpt` of a run `resume=` continues, or None.
        model_config: the config the model is built from (a checkpoint's, with `model.*` overrides on top).
        solver: the ODE solver models integrate with.
        data: the `data.*` options as plain values.
        horizons: `eval.horizons` that fit the record.
        cache_dir: where simulated datasets are cached (None: not cached).
        system_config: the system's config as plain data (part of a simulated dataset's cache key).
        model, splits: the model built for the data, and the data's train/val/test (None where the command
            builds them later: `mpsim simulate`).
        dist: this process's place in a `torchrun` job (a single process by default).
    """

    runtime: Runtime
    mode: str
    seed: int
    system: System | None
    checkpoint: dict[str, Any] | None
    resumed: dict[str, Any] | None
    model_config: dict[str, Any]
    solver: ODESolver
    data: DataOptions
    horizons: list[int]
    cache_dir: Path | None = None
    system_config: dict[str, Any] = field(default_factory=dict)
    model: Model | None = None
    splits: Splits | None = None
    dist: DistContext = field(default=SINGLE)

    @property
    def start(self) -> dict[str, Any] | None:
        """The checkpoint the model's weights come from: the resumed run's last.ckpt, or `init=`'s."""
        return self.resumed if self.resumed is not None else self.checkpoint

    def build_model(self, shape: Shape, ckpt: dict[str, Any] | None = None, training: bool = False) -> Model:
        """A model of this job's config for data of `shape` (with `ckpt`'s weights), checked before allocation."""
        return build_model_for(self.model_config, self.solver, self.runtime, shape, ckpt, training)


def resolve_mode(name: str, init: str | None) -> str:
    """scratch (default) becomes finetune when `init=` is given; finetune and zeroshot need `init=`."""
    if name not in MODES:
        raise ConfigError(f"mode={name!r} is unknown; choose one of {', '.join(MODES)}.")
    if name == "scratch":
        return "finetune" if init else "scratch"
    if not init:
        raise ConfigError(f"mode={name} needs init=<checkpoint> (a path, or a name in paths.ckpt_dir).")
    return name


def prepare(
    cfg: DictConfig,
    command: str,
    output_dir: str | Path | None = None,
    overrides: list[str] | None = None,
    *,
    training: bool = False,
    distributed_run: bool = False,
    with_data: bool = True,
) -> Job:
    """Check `cfg`, set up the runtime and build what `mpsim <command>` computes with.

    Args:
        command: train | eval | diagnose | simulate.
        output_dir, overrides: the run directory and command-line overrides (default: Hydra's).
        training: the model will be trained (its memory check counts gradients and optimiser state).
        distributed_run: join a `torchrun` process group (`mpsim train`); rank 0 simulates the data first.
        with_data: load the data and build the model for it (`mpsim simulate` builds its model later).
    """
    for key in ("system", "model"):  # a spec file's content replaces its name: checkpoints carry the equations
        node = cfg.get(key)
        if isinstance(node, DictConfig) and isinstance(node.get("spec"), str):
            path = resolve_path(node.spec, start_directory())
            with open_dict(cfg):
                node.spec = load_spec_file(path)
                if key == "system" and "name" in node and node.name is None and not node.spec.get("name"):
                    node.name = file_stem(path) or "equations"
    validate_values(cfg)
    check_targets(cfg)
    rt = make_runtime(
        seed=int(cfg.seed),
        device=str(cfg.device),
        dtype=str(cfg.dtype),
        threads=cfg.get("threads"),
        output_dir=output_dir,
        overrides=overrides,
        memory_check=bool(cfg.get("memory_check", True)),
    )
    mode = resolve_mode(cfg.mode.name, cfg.init) if command == "train" else command
    resumed = None
    if command == "train" and cfg.get("resume"):
        resumed = load_resumed(rt.output_dir, int(cfg.trainer.max_epochs), int(cfg.trainer.early_stop_patience))
    model_node = plain_dict(cfg.model) if cfg.get("model") is not None else {}
    ckpt = load_init(cfg.init, rt, cfg.paths.ckpt_dir, model_node) if resumed is None else None
    data = DataOptions(**plain_dict(cfg.data))
    job = Job(
        runtime=rt,
        mode=mode,
        seed=int(cfg.seed),
        system=build(plain_dict(cfg.system), "system") if not data.from_file or data.graph == "system" else None,
        checkpoint=ckpt,
        resumed=resumed,
        model_config=model_config(model_node, resumed or ckpt, rt.overrides),
        solver=build(plain_dict(cfg.solver), "solver"),
        data=data,
        horizons=[int(h) for h in cfg.eval.horizons],
        cache_dir=resolve_path(cfg.paths.cache_dir, rt.start_dir) if data.cache else None,
        system_config=plain_dict(cfg.system),
    )
    if not with_data:
        return job
    refit = command == "train" and resumed is None and bool(cfg.mode.refit_normalisation)
    ctx = distributed.setup(rt.device) if distributed_run else SINGLE
    try:
        return with_model_and_data(job, ctx, given(rt.overrides, "eval.horizons"), training, refit)
    except BaseException:
        distributed.teardown(ctx, together=False)
        raise


def with_model_and_data(job: Job, ctx: DistContext, explicit_horizons: bool, training: bool, refit: bool) -> Job:
    """`job` with its data loaded and its model built for them, checked in the order that writes nothing before
    a bad input is found: a file is read first (its shape decides the model's), a simulation only once the model
    fits the system. Under `torchrun` rank 0 simulates (and caches) the data first; the other ranks then read
    the cache."""
    need = ("test",) if job.mode in ("zeroshot", "eval") else SPLITS
    rt, data, system = job.runtime, job.data, job.system
    if not ctx.is_main:
        ctx.barrier()
    dtype_name = str(rt.dtype).split(".")[-1]
    graph = None if system is None else system.edge_index
    splits = load_splits(data, rt.start_dir, dtype_name, need, system_graph=graph) if data.from_file else None
    horizons = job.horizons
    if splits is not None:
        steps = next(s for s in (splits.train, splits.test, splits.val) if len(s)).n_times - 1
        horizons = fit_horizons(horizons, explicit_horizons, steps, f"data.path={data.path}")
    source = (splits.train if len(splits.train) else splits.test) if splits else system
    if source is None:
        raise ConfigError("no data: pass system=<name> or data.path=<file>.")
    model = job.build_model(Shape.of(source), job.start, training)
    if splits is None:
        assert system is not None  # the source above
        horizon = int(data.horizon or system.horizon)
        horizons = fit_horizons(horizons, explicit_horizons, horizon, f"system={system.name} with {horizon} steps")
        sizes = [data.n_train, data.n_val, data.n_test]
        check_simulation_memory(system, sizes, int(data.burn_in) + horizon + 1, rt.memory_check)
        splits = load_splits(
            data, rt.start_dir, dtype_name, system=system, system_config=job.system_config, cache_dir=job.cache_dir
        )
    if job.start is None or refit:
        model.set_normalisation(*fit_normalisation(splits.train))
    if ctx.is_main:
        ctx.barrier()
    return replace(job, model=model, splits=splits, horizons=horizons, dist=ctx)
