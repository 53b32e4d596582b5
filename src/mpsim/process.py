"""Process-wide settings for a command-line run, made by the entry points and never at import.

`mpsim.cli.main` (the `mpsim` console script, `python -m mpsim`, `torchrun -m mpsim`, and so every command,
`mpsim bench` included) calls `configure_process()` first, before torch is imported, and a command's task
calls it again in the worker processes of a Hydra launcher (joblib, submitit). A program that imports mpsim as
a library keeps its environment and its allocator as they were.
"""

from __future__ import annotations

import ctypes
import os
import re
import sys
from typing import TYPE_CHECKING

from mpsim.errors import ConfigError

if TYPE_CHECKING:
    import torch

#: the values `device=` takes
DEVICE = re.compile(r"auto|cpu|mps|cuda(:\d+)?")


def configure_process() -> bool:
    """Back large CPU tensors by transparent huge pages and keep freed CPU memory for reuse.

    `THP_MEM_ALLOC_ENABLE=1` (unless the user set it) backs CPU tensors of 2 MB and more by transparent huge
    pages. Torch's allocator reads it once, so it must be set before torch is first imported: a fresh 184 MB
    tensor then costs ~45 instead of ~90 ms of page faults, which makes a long S-MNN solve (T = 5000, 1536
    columns: a dozen such tensors per step) ~25 % faster. No effect on GPU memory or where the kernel does not
    offer THP; `THP_MEM_ALLOC_ENABLE=0` turns it off.

    Returns whether glibc now keeps freed memory (`keep_freed_cpu_memory`).
    """
    os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")
    return keep_freed_cpu_memory()


def keep_freed_cpu_memory() -> bool:
    """Let glibc keep freed CPU memory for reuse instead of returning it to the kernel (Linux/glibc only).

    PyTorch's CPU allocator is plain malloc: every tensor over 32 MB is a fresh mmap, so each large intermediate
    is paid for again in page faults (and, with huge pages, in the kernel's compaction, which on a busy machine
    took 0.3-3 s of system time per S-MNN step at T = 5000). Serving large blocks from the heap and never
    trimming it makes a steady-state step fault-free, the CPU counterpart of the CUDA caching allocator
    (S-MNN fwd+bwd at T = 5000, batch 512: 0.86-3.0 s -> 0.66-0.71 s). The cost: memory freed by a run is
    kept by the process until it exits. `MPSIM_KEEP_HEAP=0` turns this off.
    """
    if os.environ.get("MPSIM_KEEP_HEAP", "1") == "0" or not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (e.g. musl): leave the allocator alone
        return False
    m_trim_threshold, m_mmap_max = -1, -4
    return bool(mallopt(m_mmap_max, 0)) and bool(mallopt(m_trim_threshold, 2**31 - 1))


def resolve_device(device: str) -> torch.device:
    """The torch device for `device=` (auto: CUDA when there is one), refused when this machine lacks it."""
    import torch

    if not DEVICE.fullmatch(device):
        raise ConfigError(f"device={device} is not supported; choose auto, cpu, cuda, cuda:<index> or mps.")
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"device={device} but CUDA is not available on this machine; use device=cpu.")
    if device.startswith("cuda:") and int(device[5:]) >= torch.cuda.device_count():
        count = torch.cuda.device_count()
        raise ConfigError(f"device={device} but this machine has {count} CUDA device(s), cuda:0 to cuda:{count - 1}.")
    if device == "mps" and not torch.backends.mps.is_available():
        raise ConfigError("device=mps but Apple's MPS backend is not available on this machine; use device=cpu.")
    return torch.device(device)
