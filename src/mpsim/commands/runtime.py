"""Where and how a command runs: checks the composed config, seeds, sets threads, picks device and dtype, and
resolves paths against the directory the command was started from (`Runtime`).

This is the command layer: the only code that reads config objects. Everything below it takes plain arguments.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, open_dict

from mpsim.config import check_targets, file_stem, validate_values
from mpsim.errors import ConfigError
from mpsim.process import resolve_device

DTYPES = {"float32": torch.float32, "float64": torch.float64}


@dataclass
class Runtime:
    device: torch.device
    dtype: torch.dtype
    start_dir: Path
    output_dir: Path
    overrides: list[str]


def hydra_overrides() -> list[str]:
    """The task overrides given on the command line (empty outside a Hydra run)."""
    if HydraConfig.initialized():
        return list(HydraConfig.get().overrides.task)
    return []


def is_multirun() -> bool:
    """Whether this process runs a job of a Hydra sweep (`-m`)."""
    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def locate(output_dir: str | Path | None = None) -> tuple[Path, Path]:
    """(directory the command was started from, this run's output directory), created if needed."""
    if HydraConfig.initialized():
        hc = HydraConfig.get()
        start_dir, output_dir = Path(hc.runtime.cwd), Path(output_dir or hc.runtime.output_dir)
    else:
        start_dir, output_dir = Path.cwd(), Path(output_dir or Path.cwd())
    output_dir.mkdir(parents=True, exist_ok=True)
    return start_dir, output_dir


def setup_runtime(cfg: DictConfig, output_dir: str | Path | None = None, overrides: list[str] | None = None) -> Runtime:
    """Check `_target_` nodes, seed, set threads and pick device/dtype; return where things go."""
    inline_specs(cfg)
    validate_values(cfg)
    check_targets(cfg)
    start_dir, output_dir = locate(output_dir)
    threads = cfg.get("threads")
    if threads is None and HydraConfig.initialized():
        launcher = HydraConfig.get().launcher
        if "joblib" in str(launcher.get("_target_", "")):
            n_jobs = int(launcher.get("n_jobs", -1) or -1)
            if n_jobs < 1:
                n_jobs = os.cpu_count() or 1
            threads = max(1, (os.cpu_count() or 1) // n_jobs)
    if threads:
        torch.set_num_threads(int(threads))
    torch.manual_seed(int(cfg.seed))
    if cfg.dtype not in DTYPES:
        raise ConfigError(f"dtype={cfg.dtype!r} is not supported; choose one of {sorted(DTYPES)}.")
    return Runtime(
        device=resolve_device(str(cfg.device)),
        dtype=DTYPES[cfg.dtype],
        start_dir=start_dir,
        output_dir=output_dir,
        overrides=hydra_overrides() if overrides is None else list(overrides),
    )


def describe_device(device: torch.device) -> str:
    """Where a run computed, for its summary: `cpu (2 threads)` or `cuda:0 (NVIDIA H100 80GB HBM3)`."""
    if device.type == "cuda":
        index = torch.cuda.current_device() if device.index is None else device.index
        return f"cuda:{index} ({torch.cuda.get_device_name(index)})"
    return f"{device.type} ({torch.get_num_threads()} thread{'s' if torch.get_num_threads() != 1 else ''})"


def inline_specs(cfg: DictConfig) -> None:
    """`system.spec=<file>` / `model.spec=<file>` (model=equations, system=equations): replace the file name by
    the file's content, so that checkpoints, dataset cache keys and summaries carry the equations themselves."""
    from mpsim.spec import load_spec_file

    start_dir = Path(HydraConfig.get().runtime.cwd) if HydraConfig.initialized() else Path.cwd()
    for key in ("system", "model"):
        node = cfg.get(key)
        if not isinstance(node, DictConfig) or not isinstance(node.get("spec"), str):
            continue
        path = resolve_path(node.spec, start_dir)
        content = load_spec_file(path)
        with open_dict(cfg):
            node.spec = content
            if key == "system" and "name" in node and node.name is None and not content.get("name"):
                node.name = file_stem(path) or "equations"


def resolve_path(path: str | Path, start_dir: Path) -> Path:
    """An absolute path as given, else relative to the directory the command was started from."""
    path = Path(os.path.expanduser(str(path)))
    return path if path.is_absolute() else start_dir / path
