"""Measuring tools for `mpsim bench`: timing, peak memory and scaling exponents.

Benchmarks report ratios measured side by side in one run (these machines are shared and noisy), never
absolute times asserted in tests.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import resource
import statistics
import time
from collections.abc import Callable, Sequence
from typing import Any

import torch

from mpsim import process
from mpsim.errors import ConfigError


def timeit(fn: Callable[[], Any], repeats: int = 5, warmup: int = 1, max_seconds: float = 30.0) -> dict[str, float]:
    """Median and minimum wall time of `fn()` over `repeats` runs after `warmup` runs (fewer if slow).

    Returns:
        {"median_s", "min_s", "runs"}.
    """
    for _ in range(warmup):
        fn()
    times: list[float] = []
    start = time.perf_counter()
    for _ in range(repeats):
        cuda_sync()
        t0 = time.perf_counter()
        fn()
        cuda_sync()
        times.append(time.perf_counter() - t0)
        if time.perf_counter() - start > max_seconds:
            break
    return {"median_s": statistics.median(times), "min_s": min(times), "runs": len(times)}


def resolve_device(device: str) -> str:
    """A suite's `device=`: `auto` becomes `cuda` when one is available, else `cpu` (`mpsim.process.resolve_device`,
    which refuses a device this machine lacks); the suites run on cpu or cuda[:i] only."""
    chosen = process.resolve_device(device)
    if chosen.type not in ("cpu", "cuda"):
        raise ConfigError(f"device must be cpu, cuda or auto; got {device!r}.")
    return str(chosen)


def cuda_sync() -> None:
    """Wait for queued CUDA work (kernels run asynchronously: a timing must not stop before they finish)."""
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        torch.cuda.synchronize()


def _rss_kib(field: str) -> int | None:
    """VmRSS or VmHWM of this process in KiB (Linux), or None."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        pass
    return None


def _child(fn: Callable[[], Any], threads: int, queue: Any) -> None:
    torch.set_num_threads(threads)
    try:  # restart the high-water mark at the current size: import-time peaks are not fn's
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        base = _rss_kib("VmRSS")
    except OSError:
        base = None
    if base is None:
        base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    try:
        fn()
        peak = _rss_kib("VmHWM") or resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        queue.put(("ok", (peak - base) / 1024.0))
    except Exception as err:  # noqa: BLE001 - report any failure of the measured code
        queue.put(("error", f"{type(err).__name__}: {err}"))


def peak_memory_mb(fn: Callable[[], Any], threads: int = 1, timeout: float = 600.0) -> float:
    """Peak resident-memory growth (MiB) while `fn()` runs, measured in a fresh process.

    `fn` must be picklable (a module-level function or a `functools.partial` of one). The child's baseline
    is taken after its imports (and its high-water mark reset there), so the number is what `fn` itself
    allocated at its peak. NaN on failure. The child is spawned, not forked (a forked child deadlocks in
    OpenMP once the parent has used its thread pool), and it returns freed memory to the kernel (glibc's
    default: the child is not set up by `mpsim.process.configure_process`, which only the entry point calls),
    otherwise pages freed during its imports would absorb fn's allocations unseen.
    """
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_child, args=(fn, threads, queue))
    proc.start()
    proc.join(timeout)
    if proc.is_alive():
        proc.kill()
        return math.nan
    if queue.empty():
        return math.nan
    status, value = queue.get()
    return value if status == "ok" else math.nan


def scaling_exponent(sizes: Sequence[float], values: Sequence[float]) -> float:
    """Least-squares slope of log(value) against log(size): 1 = linear, 2 = quadratic (NaN if < 2 points)."""
    pts = [(math.log(s), math.log(v)) for s, v in zip(sizes, values, strict=True) if s > 0 and v and v > 0]
    if len(pts) < 2:
        return math.nan
    mx = sum(p[0] for p in pts) / len(pts)
    my = sum(p[1] for p in pts) / len(pts)
    sxx = sum((p[0] - mx) ** 2 for p in pts)
    return sum((p[0] - mx) * (p[1] - my) for p in pts) / sxx if sxx else math.nan


class Suite:
    """A benchmark suite: `run()` returns one row (a flat dict) per measured case.

    Subclasses take their sizes as constructor arguments (from `conf/bench/<suite>.yaml`) and may override
    `summarise(rows)` (ratios, fitted exponents: Markdown lines under the table) and `plot(rows, out_dir)`.
    """

    name = "suite"

    def run(self) -> list[dict[str, Any]]:
        raise NotImplementedError

    def summarise(self, rows: list[dict[str, Any]]) -> list[str]:
        return []

    def plot(self, rows: list[dict[str, Any]], out_dir: Any) -> list[str]:
        return []
