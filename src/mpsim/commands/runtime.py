"""Where and how a command runs (`Runtime`): device and dtype, the directory it was started from and its run
directory, the overrides it was given, whether sizes are checked against memory; seeding and threads; paths
resolved against the start directory. Plain values in: `mpsim.commands.prepare` reads them from the config.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode

from mpsim.errors import ConfigError
from mpsim.process import resolve_device

DTYPES = {"float32": torch.float32, "float64": torch.float64}


@dataclass(frozen=True)
class Runtime:
    """Where and how a command computes and writes.

    Attributes:
        device, dtype: what models compute on and in.
        start_dir: the directory the command was started from (relative paths are read from it).
        output_dir: this run's directory.
        overrides: the command line's overrides (which `model.*` keys were given explicitly, ...).
        memory_check: refuse sizes whose memory estimate does not fit (`memory_check=false` skips).
    """

    device: torch.device
    dtype: torch.dtype
    start_dir: Path
    output_dir: Path
    overrides: list[str]
    memory_check: bool = True


def hydra_overrides() -> list[str]:
    """The task overrides given on the command line (empty outside a Hydra run)."""
    if HydraConfig.initialized():
        return list(HydraConfig.get().overrides.task)
    return []


def is_multirun() -> bool:
    """Whether this process runs a job of a Hydra sweep (`-m`)."""
    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def start_directory() -> Path:
    """The directory the command was started from (Hydra's record of it, or the current directory)."""
    return Path(HydraConfig.get().runtime.cwd) if HydraConfig.initialized() else Path.cwd()


def locate(output_dir: str | Path | None = None) -> tuple[Path, Path]:
    """(directory the command was started from, this run's output directory), created if needed."""
    if HydraConfig.initialized():
        hc = HydraConfig.get()
        start_dir, output_dir = Path(hc.runtime.cwd), Path(output_dir or hc.runtime.output_dir)
    else:
        start_dir, output_dir = Path.cwd(), Path(output_dir or Path.cwd())
    output_dir.mkdir(parents=True, exist_ok=True)
    return start_dir, output_dir


def launcher_threads() -> int | None:
    """Threads per job when Hydra's joblib launcher runs jobs side by side (cores / jobs), else None."""
    if not HydraConfig.initialized():
        return None
    launcher = HydraConfig.get().launcher
    if "joblib" not in str(launcher.get("_target_", "")):
        return None
    n_jobs = int(launcher.get("n_jobs", -1) or -1)
    if n_jobs < 1:
        n_jobs = os.cpu_count() or 1
    return max(1, (os.cpu_count() or 1) // n_jobs)


def make_runtime(
    *,
    seed: int,
    device: str,
    dtype: str,
    threads: int | None,
    output_dir: str | Path | None = None,
    overrides: list[str] | None = None,
    memory_check: bool = True,
) -> Runtime:
    """Seed torch, set its CPU threads (None: the launcher's share, else torch's default) and pick device and
    dtype; the run directory is created."""
    if dtype not in DTYPES:
        raise ConfigError(f"dtype={dtype!r} is not supported; choose one of {sorted(DTYPES)}.")
    start_dir, out_dir = locate(output_dir)
    threads = threads if threads is not None else launcher_threads()
    if threads:
        torch.set_num_threads(int(threads))
    torch.manual_seed(int(seed))
    return Runtime(
        device=resolve_device(device),
        dtype=DTYPES[dtype],
        start_dir=start_dir,
        output_dir=out_dir,
        overrides=hydra_overrides() if overrides is None else list(overrides),
        memory_check=memory_check,
    )


def describe_device(device: torch.device) -> str:
    """Where a run computed, for its summary: `cpu (2 threads)` or `cuda:0 (NVIDIA H100 80GB HBM3)`."""
    if device.type == "cuda":
        index = torch.cuda.current_device() if device.index is None else device.index
        return f"cuda:{index} ({torch.cuda.get_device_name(index)})"
    return f"{device.type} ({torch.get_num_threads()} thread{'s' if torch.get_num_threads() != 1 else ''})"


def resolve_path(path: str | Path, start_dir: Path) -> Path:
    """An absolute path as given, else relative to the directory the command was started from."""
    path = Path(os.path.expanduser(str(path)))
    return path if path.is_absolute() else start_dir / path


def given(overrides: list[str], key: str) -> bool:
    """Whether `key` was given on the command line."""
    return any(a.split("=", 1)[0].lstrip("+~") == key for a in overrides)
