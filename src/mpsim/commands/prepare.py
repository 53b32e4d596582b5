"""The composition root: `prepare(cfg, command) -> Job`, the one function below the `run_<command>` wrappers that
reads the config. It checks the composed config, sets up where and how the command runs, finds the starting
checkpoint (or the run being resumed), builds the system, the solver and the model, and loads the data through
the pipeline (`mpsim.data.pipeline`) — in the order that writes nothing before a bad input is found: the model
is checked against the system before any data is simulated into the cache. Everything it hands on is a plain
value or an object built from one.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
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
from mpsim.files import file_sha256
from mpsim.models.base import Model
from mpsim.models.latent import estimate_pending
from mpsim.solvers.odeint import ODESolver
from mpsim.spec import load_spec_file
from mpsim.spec.parse import MODEL_KEYS, SYSTEM_KEYS, merge_spec, parse_spec
from mpsim.systems.base import System
from mpsim.training import distributed
from mpsim.training.distributed import SINGLE, DistContext

log = logging.getLogger(__name__)

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


def _input_files(system: Any) -> list[Any]:
    """The `system.input` nodes that read a file (config or plain data): the input itself, or per input
    (`{u: {file: ...}}`)."""
    node = system.get("input") if isinstance(system, Mapping) else None
    if not isinstance(node, Mapping):
        return []
    if "file" in node:
        return [node]
    return [v for v in node.values() if isinstance(v, Mapping) and "file" in v]


def _with_input_hashes(system_config: dict[str, Any]) -> dict[str, Any]:
    """The system's config as the cache key: with the SHA-256 of each input file, so an edited file is simulated
    anew."""
    files = [Path(str(n["file"])) for n in _input_files(system_config)]
    hashes = [file_sha256(f) for f in files if f.is_file()]
    return {**system_config, "input_sha256": hashes} if hashes else system_config


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
    for node in _input_files(cfg.get("system")):  # an input file, relative to where mpsim was started
        if isinstance(node.file, str) and node.file.strip():
            with open_dict(node):
                node.file = str(resolve_path(node.file, start_directory()))
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
        system_config=_with_input_hashes(plain_dict(cfg.system)),
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


@dataclass(frozen=True)
class ModelNames:
    """The names a model states (a spec's, `model=equations`): the data's columns (its states, then its
    outputs), {s: o} for each equation o' = s (how a state the data lack is first estimated), its inputs and
    outputs. All None/empty for a model that takes the data's names."""

    columns: list[str] | None = None
    rates: dict[str, str] = field(default_factory=dict)
    inputs: list[str] | None = None
    outputs: list[str] = field(default_factory=list)


def spec_states(model_cfg: dict[str, Any]) -> ModelNames:
    """The names `model_cfg`'s spec states (`ModelNames`)."""
    if not any(model_cfg.get(k) for k in ("spec", "states", "equations")):
        return ModelNames()
    inline = {k: model_cfg.get(k) for k in MODEL_KEYS if k != "spec"}
    spec = parse_spec(merge_spec(model_cfg.get("spec"), inline, "model"), "model.spec", extra_keys=SYSTEM_KEYS)
    return ModelNames(list(spec.columns), spec.rates(), list(spec.inputs), list(spec.outputs))


def _refuse_inputs_read_as_states(inputs: list[str] | None, splits: Splits, data: DataOptions) -> None:
    """A spec's inputs that a batch file (npz, long CSV) holds as state columns because `data.control_columns`
    does not list them: say so, rather than that the data have no controls."""
    part = next((s for s in (splits.train, splits.test, splits.val) if len(s)), splits.test)
    as_states = [n for n in inputs or [] if n in part.state_names and n not in part.control_names]
    if as_states and not data.control_columns:
        raise ConfigError(
            f"the model's inputs {inputs} are columns of {data.path}, read as states because data.control_columns "
            f"does not list them. Add data.control_columns={list(inputs or [])}."
        )


def with_latent_estimates(model: Model, splits: Splits) -> Splits:
    """`splits` with the latent states no measured state is the rate of (``meta['pending']``) estimated through
    `model` (`mpsim.models.latent`) in every split. The whole test records are left to the free run, which
    estimates their start from their first samples only (`mpsim.models.freerun`)."""
    parts = {name: getattr(splits, name) for name in ("train", "val", "test")}
    pending = next((p.meta["pending"] for p in parts.values() if p.meta.get("pending")), None)
    if pending is None:
        return splits
    log.info(f"estimating {pending} through the model (unscented Kalman smoother)")
    return replace(splits, **{name: estimate_pending(model, part) for name, part in parts.items()})


def _warn_other_hold(ckpt: dict[str, Any] | None, splits: Splits) -> None:
    """Warn when the data hold their inputs between samples otherwise than the data the checkpoint was fitted to
    (`data.input_hold`): a model fitted with `zoh` inputs and run with `linear` ones sees other forces."""
    if ckpt is None:
        return
    data = next((s for s in (splits.train, splits.test, splits.val) if len(s)), splits.test)
    if data.u is None:
        return
    trained, now = ckpt.get("system", {}).get("input_hold"), data.meta.get("input_hold", "linear")
    if trained is not None and trained != now:
        log.warning(
            f"{ckpt.get('path')} was fitted to inputs held '{trained}' between samples, but these data hold them "
            f"'{now}' (data.input_hold={now}): the model sees other forces than it was fitted to. Give "
            f"data.input_hold={trained} unless the new data are held otherwise."
        )


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
    splits = None
    if data.from_file:
        names = spec_states(job.model_config)
        splits = load_splits(
            data,
            rt.start_dir,
            dtype_name,
            need,
            system_graph=graph,
            states=names.columns,
            rates=names.rates,
            inputs=names.inputs,
            memory_check=rt.memory_check,
            outputs=names.outputs,
        )
        _refuse_inputs_read_as_states(names.inputs, splits, data)
    horizons = job.horizons
    if splits is not None:
        _warn_other_hold(job.start, splits)
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
    if data.from_file:
        splits = with_latent_estimates(model, splits)
    if job.start is None or refit:
        model.set_normalisation(*fit_normalisation(splits.train))
    if ctx.is_main:
        ctx.barrier()
    return replace(job, model=model, splits=splits, horizons=horizons, dist=ctx)
