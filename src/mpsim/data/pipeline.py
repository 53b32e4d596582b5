"""A command's data as one pipeline of small steps, composed in one place (`load_splits`) from plain options.

Measured data: read (by the file's extension: `.npz`, long `.csv`) → map columns (controls apart from states) →
check that the model's precision holds them → split by trajectory → (the caller) normalise with the training
split's statistics. Recordings (wide `.csv` or `.mat` files, one per recording, several by a glob) take the
steps of `mpsim.data.measured` (map columns, one grid, stride, latent states, segments) and are split into
contiguous blocks in time order. Simulated data: simulate the three splits from their own seed streams (cached). Each step is a
function with one job; a new reader or step slots in here without touching the others.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from mpsim.data.account import split_covers, split_lines
from mpsim.data.dataset import SPLITS, DatasetSpec, Simulator, Splits, simulate_splits, split_trajectories
from mpsim.data.io import load_trajectories
from mpsim.data.keys import check_data_names
from mpsim.data.measured import Recordings, is_recording, paths_of, read_recordings
from mpsim.data.official import RANGE_KEYS, check_range, official_splits
from mpsim.data.precision import check_representable
from mpsim.data.segments import contiguous_split
from mpsim.data.trajectories import Trajectories
from mpsim.errors import ConfigError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DataOptions:
    """Where a command's data come from and how they are split: the `data.*` keys, as plain values (their
    defaults and meanings: `mpsim.config`'s `DataConf`, which `tests/test_defaults.py` holds to these)."""

    path: str | None = None
    test_path: str | None = None
    train_range: list[int] | None = None
    val_range: list[int] | None = None
    test_range: list[int] | None = None
    edges: str | None = None
    graph: str | None = None
    control_columns: list[str] = field(default_factory=list)
    time_column: str | None = "t"
    columns: Mapping[str, str] | None = None
    observed: list[str] = field(default_factory=list)
    resample: float | None = None
    stride: int = 1
    segment: float | None = None
    input_hold: str = "linear"
    n_train: int = 200
    n_val: int = 50
    n_test: int = 50
    split: list[float] = field(default_factory=lambda: [0.7, 0.15, 0.15])
    dt: float | None = None
    horizon: int | None = None
    burn_in: int = 0
    seed: int = 0
    noise_std: float = 0.0
    cache: bool = True
    gt_rtol: float = 1.0e-8
    gt_atol: float = 1.0e-10

    @property
    def from_file(self) -> bool:
        return bool(self.path)

    @property
    def official(self) -> bool:
        """Whether the data come split by file or row range (`data.test_path`, `data.*_range`)."""
        return bool(self.test_path) or any(getattr(self, k) is not None for k in RANGE_KEYS)

    def recordings(
        self,
        states: Sequence[str] | None,
        rates: Mapping[str, str],
        inputs: Sequence[str] | None = None,
        dtype_name: str = "float64",
        memory_check: bool = True,
        outputs: Sequence[str] = (),
    ) -> Recordings:
        """How recordings become a batch, for a model with `states` and `inputs` (None: the file's), `rates`
        ({s: o} for each equation o' = s: how a latent state is estimated) and precision `dtype_name`."""
        columns = self.columns or {}
        if not isinstance(columns, Mapping) or not all(isinstance(v, str) for v in columns.values()):
            raise ConfigError(
                f"data.columns must map model names to file columns, e.g. data.columns='{{q: position, u: torque}}'; "
                f"got {columns!r}."
            )
        check_data_names(columns, self.observed, self.control_columns, states, inputs, outputs)
        return Recordings(
            time_column=self.time_column,
            dt=self.dt,
            columns={str(k): str(v) for k, v in columns.items()},
            controls=list(self.control_columns),
            observed=list(self.observed),
            states=None if states is None else list(states),
            rates=dict(rates),
            resample=self.resample,
            stride=self.stride,
            segment=self.segment,
            input_hold=self.input_hold,
            inputs=None if inputs is None else list(inputs),
            dtype_name=dtype_name,
            memory_check=memory_check,
            outputs=tuple(outputs),
        )

    def dataset_spec(self, system_config: dict[str, Any]) -> DatasetSpec:
        """What a simulated dataset is (its cache key): the system's config and the sizes, seed and sampling."""
        return DatasetSpec(
            system=system_config,
            n_train=self.n_train,
            n_val=self.n_val,
            n_test=self.n_test,
            seed=self.seed,
            dt=self.dt,
            horizon=self.horizon,
            burn_in=self.burn_in,
            rtol=self.gt_rtol,
            atol=self.gt_atol,
        )


def resolve(path: str | Path, start_dir: Path) -> Path:
    """A path as given when absolute (`~` expanded), else relative to the directory the command was started from."""
    path = Path(path).expanduser()
    return path if path.is_absolute() else start_dir / path


def file_graph(options: DataOptions, system_graph: torch.Tensor | None) -> torch.Tensor | None:
    """The graph a file without its own takes: the system's with `data.graph=system` (else None: the file's)."""
    if options.graph == "system":
        if system_graph is None:
            raise ConfigError("data.graph=system needs system=<name>.")
        return system_graph
    if options.graph is not None:
        raise ConfigError(f"data.graph={options.graph!r}: use null (graph from the file) or 'system'.")
    return None


def is_recordings(options: DataOptions, start_dir: Path) -> bool:
    """Whether `data.path` names recordings (wide CSV or `.mat` files, or a glob of them)."""
    assert options.path is not None
    files = paths_of(resolve(options.path, start_dir))
    return len(files) > 1 or is_recording(files[0])


def read(
    options: DataOptions,
    start_dir: Path,
    system_graph: torch.Tensor | None = None,
    states: Sequence[str] | None = None,
    rates: Mapping[str, str] | None = None,
    inputs: Sequence[str] | None = None,
    dtype_name: str = "float64",
    memory_check: bool = True,
    outputs: Sequence[str] = (),
) -> Trajectories:
    """Read step: `data.path` by its extension, with its graph (an edge list, or the system's) and the columns
    that are controls (`data.control_columns`); recordings (`is_recordings`) through `mpsim.data.measured`, as
    the model's `states` and `inputs` (None: the file's), latent ones estimated by `rates`."""
    assert options.path is not None
    if is_recordings(options, start_dir):
        how = options.recordings(states, rates or {}, inputs, dtype_name, memory_check, outputs)
        return read_recordings(resolve(options.path, start_dir), how)
    _refuse_recording_keys(options)
    edges = resolve(options.edges, start_dir) if options.edges else None
    loaded = load_trajectories(
        resolve(options.path, start_dir), edges, file_graph(options, system_graph), list(options.control_columns)
    )
    loaded.meta.setdefault("input_hold", options.input_hold)
    log.info(
        f"loaded {len(loaded)} trajectories from {options.path}: T={loaded.n_times}, N={loaded.n_nodes}, "
        f"D={loaded.state_dim}"
    )
    return loaded


def _refuse_recording_keys(options: DataOptions) -> None:
    """The keys that concern recordings only are refused for a batch file (npz, long CSV), not ignored."""
    given = {
        "data.columns": bool(options.columns),
        "data.observed": bool(options.observed),
        "data.resample": options.resample is not None,
        "data.stride": options.stride != 1,
        "data.segment": options.segment is not None,
    }
    used = [key for key, on in given.items() if on]
    if used:
        raise ConfigError(
            f"{', '.join(used)} apply to recordings (a wide CSV or .mat file per recording); data.path={options.path} "
            "is a batch of trajectories (npz or long CSV with traj, t, node columns). Drop them, or give recordings."
        )


def load_splits(
    options: DataOptions,
    start_dir: Path,
    dtype_name: str,
    need: tuple[str, ...] = SPLITS,
    system: Simulator | None = None,
    system_graph: torch.Tensor | None = None,
    system_config: dict[str, Any] | None = None,
    cache_dir: Path | None = None,
    states: Sequence[str] | None = None,
    rates: Mapping[str, str] | None = None,
    inputs: Sequence[str] | None = None,
    memory_check: bool = True,
    outputs: Sequence[str] = (),
) -> Splits:
    """The data of a command, train/val/test: a file read and split by trajectory (the splits in `need` get a
    share > 0), or the system's three splits simulated (cached in `cache_dir`; None: no cache).

    Args:
        dtype_name: the model's precision (`float32`/`float64`): a file's values must fit it.
        system, system_graph, system_config: the ground truth when simulating (its graph also serves a file
            given with `data.graph=system`); its config is part of the cache key.
        states, rates, inputs: the model's states and inputs and how its latent states are estimated (`read`).
        memory_check: refuse a recording whose reading would not fit in memory (`memory_check=false`: try).
        outputs: the model's outputs (a spec's `outputs:`): `states` lists its states, then these.

    Recordings are split into contiguous blocks in time order (`contiguous_split`); a batch file at random by
    trajectory (`data.seed`). What each split covers is logged (and kept in its ``meta['covers']``).
    """
    if options.from_file and options.official:
        assert options.path is not None
        if not is_recordings(options, start_dir):
            raise ConfigError(
                f"data.test_path and data.train_range / val_range / test_range split recordings (wide CSV or .mat "
                f"files); data.path={options.path} is a batch of trajectories, split by data.split. Drop them, or "
                "give recordings."
            )
        how = options.recordings(states, rates or {}, inputs, dtype_name, memory_check, outputs)
        ranges = {key: check_range(key, getattr(options, key)) for key in RANGE_KEYS}
        test_path = resolve(options.test_path, start_dir) if options.test_path else None
        splits = official_splits(resolve(options.path, start_dir), test_path, ranges, how, options.split, need)
        for line in split_lines(split_covers(splits)):
            log.info(line)
        return splits
    if options.from_file:
        data = read(options, start_dir, system_graph, states, rates, inputs, dtype_name, memory_check, outputs)
        check_representable(data, dtype_name, str(options.path))
        if "segments" in data.meta:
            splits = contiguous_split(data, tuple(options.split), need)
        else:
            splits = split_trajectories(data, tuple(options.split), options.seed, need)
        for line in split_lines(split_covers(splits)):
            log.info(line)
        return splits
    if system is None:
        raise ConfigError("no data: pass system=<name> or data.path=<file>.")
    return simulate_splits(system, options.dataset_spec(system_config or {}), cache_dir)


def record_steps(options: DataOptions, system: Any) -> int:
    """Steps per trajectory of the data before they are loaded: a simulated record's horizon (a file's is known
    once read)."""
    return int(options.horizon or system.horizon)
