"""Memory estimates made before a simulation, a dataset or training starts, and the check that refuses a job
that would not fit.

The estimates are deliberately simple and on the low side (they count the arrays that must exist, not every
temporary), so a refusal means the job cannot fit; a job that passes may still need more. The check compares
them with the memory available now: on the CPU, the smaller of the kernel's `MemAvailable` and the room left
under the process's cgroup limit; on a CUDA device, its free memory. `memory_check=false` turns it off.
"""

from __future__ import annotations

import os
from pathlib import Path

from mpsim.errors import ResourceError

FLOAT64 = 8
# Working arrays of a ground-truth solve beyond the stored output, in units of one [B, N, D] float64 state:
# dopri5 keeps 7 stages plus error/interpolation buffers; velocity Verlet keeps positions, velocities and two
# accelerations plus pair tiles.
SOLVER_STATES = 16


def fmt_bytes(n: float) -> str:
    """`n` bytes in human units (1 kB = 1000 B)."""
    for unit in ("B", "kB", "MB", "GB", "TB", "PB"):
        if abs(n) < 1000 or unit == "PB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.3g} {unit}"
        n /= 1000
    return f"{n:.3g} PB"  # pragma: no cover


def _cgroup_room() -> int | None:
    """Bytes left under this process's cgroup (v2 or v1) memory limit, or None without a limit."""
    candidates = [
        (Path("/sys/fs/cgroup/memory.max"), Path("/sys/fs/cgroup/memory.current")),
        (Path("/sys/fs/cgroup/memory/memory.limit_in_bytes"), Path("/sys/fs/cgroup/memory/memory.usage_in_bytes")),
    ]
    for limit_path, usage_path in candidates:
        try:
            limit = limit_path.read_text().strip()
            if limit == "max" or int(limit) >= 1 << 60:
                return None
            return max(0, int(limit) - int(usage_path.read_text().strip()))
        except (OSError, ValueError):
            continue
    return None


def available_bytes(device: str = "cpu") -> int | None:
    """Memory available now on `device` ("cpu", "cuda", "cuda:1", ...), or None if it cannot be told."""
    if str(device).startswith("cuda"):
        import torch

        if not torch.cuda.is_available():
            return None
        free, _ = torch.cuda.mem_get_info(torch.device(device))
        return int(free)
    avail = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                avail = int(line.split()[1]) * 1024
                break
    except (OSError, ValueError, IndexError):
        pass
    if avail is None:
        try:
            avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):
            return None
    room = _cgroup_room()
    return avail if room is None else min(avail, room)


def trajectories_bytes(n_traj: int, n_times: int, n_nodes: int, n_features: int, itemsize: int = FLOAT64) -> int:
    """Bytes of a [B, T, N, D] array."""
    return int(n_traj) * int(n_times) * int(n_nodes) * int(n_features) * int(itemsize)


def simulation_bytes(sizes: list[int], n_times: int, n_nodes: int, state_dim: int) -> int:
    """Ground-truth simulation of datasets of `sizes` trajectories each (e.g. the three splits, all kept): their
    stored float64 outputs plus the solver's working states for the largest one."""
    out = sum(trajectories_bytes(n, n_times, n_nodes, state_dim) for n in sizes)
    return out + SOLVER_STATES * max(sizes) * int(n_nodes) * int(state_dim) * FLOAT64


def model_bytes(param_bytes: int, buffer_bytes: int, training: bool) -> int:
    """A model's weights and buffers; training adds a gradient and Adam's two moments per weight."""
    return (4 if training else 1) * int(param_bytes) + int(buffer_bytes)


def training_bytes(
    n_params: int,
    train_values: int,
    batch: int,
    n_times: int,
    n_nodes: int,
    width: int,
    itemsize: int = 4,
) -> int:
    """A crude lower bound of one training step: weights, gradients and Adam's two moments; the training split
    on the device; and a rollout of `batch` trajectories × `n_times` × `n_nodes` × `width` features kept for
    the backward pass (a handful of such tensors per step)."""
    params = 4 * int(n_params) * itemsize
    data = int(train_values) * itemsize
    activations = 6 * int(batch) * int(n_times) * int(n_nodes) * int(width) * itemsize
    return params + data + activations


def check_fits(
    need: int, what: str, device: str = "cpu", enabled: bool = True, fix: str = "", forced: bool = True
) -> None:
    """Refuse (before anything starts) a job whose estimate `need` exceeds the memory available on `device`.

    Args:
        need: estimated bytes.
        what: what was estimated, as the user asked for it (config keys and sizes).
        device: where the memory is needed.
        enabled: `memory_check` from the config (False: never refuse).
        fix: the config keys that make the job smaller.
        forced: whether `memory_check=false` lets the job try anyway (the message says so only then).

    Raises:
        ResourceError: the estimate does not fit.
    """
    if not enabled or need <= 0:
        return
    avail = available_bytes(device)
    if avail is None or need <= avail:
        return
    hint = f" ({fix})" if fix else ""
    raise ResourceError(
        f"{what} needs about {fmt_bytes(need)} of memory, but only {fmt_bytes(avail)} is available on {device}. "
        f"Make the job smaller{hint} or split it into several runs"
        + ("; memory_check=false tries anyway." if forced else ".")
    )
