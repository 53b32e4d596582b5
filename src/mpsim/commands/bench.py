"""`mpsim bench bench=<suite>`: run a benchmark suite; write bench.csv, bench.md and plots."""

from __future__ import annotations

import inspect
import logging
import platform
from pathlib import Path

import pandas as pd
import torch
from hydra.utils import get_class
from omegaconf import DictConfig

from mpsim.bench.common import Suite
from mpsim.commands.building import build
from mpsim.commands.runtime import locate
from mpsim.config import check_targets, plain_dict
from mpsim.console import markdown
from mpsim.errors import ConfigError
from mpsim.files import atomic_write, write_json

log = logging.getLogger(__name__)


def run_bench(cfg: DictConfig, output_dir: str | Path | None = None, overrides: list[str] | None = None) -> dict:
    check_targets(cfg, ("bench",))
    _, out_dir = locate(output_dir)
    if cfg.threads:
        torch.set_num_threads(int(cfg.threads))
    node = plain_dict(cfg.bench)
    suite = build(node, "bench", **device_arg(str(cfg.get("device") or "cpu"), node.get("_target_")))
    if not isinstance(suite, Suite):
        raise ConfigError(f"bench._target_={cfg.bench.get('_target_')} is not an mpsim.bench Suite.")
    machine = f"{platform.machine()}, {torch.get_num_threads()} torch thread(s), torch {torch.__version__}"
    log.info(f"bench {suite.name} on {machine}")
    rows = suite.run()
    frame = pd.DataFrame(rows)
    atomic_write(out_dir / "bench.csv", lambda f: frame.to_csv(f, index=False), mode="w")
    notes = suite.summarise(rows)
    plots = suite.plot(rows, out_dir / "plots")
    text = "\n".join([f"# mpsim bench: {suite.name}", "", f"Machine: {machine}.", "", markdown(frame), "", *notes, ""])
    atomic_write(out_dir / "bench.md", lambda f: f.write(text), mode="w")
    write_json(
        out_dir / "summary.json",
        {"task": "bench", "suite": suite.name, "rows": rows, "notes": notes, "plots": plots, "machine": machine},
    )
    print(text)
    return {"n_rows": len(rows), "bench": str(out_dir / "bench.md")}


def device_arg(device: str, target: str | None) -> dict[str, str]:
    """`device=` for a suite (`target`) that takes one; a CPU-only suite refuses any other device."""
    try:
        params = inspect.signature(get_class(str(target))).parameters
    except Exception:  # noqa: BLE001 - an unimportable target is reported by `build`
        return {}
    if "device" in params:
        return {"device": device}
    if device != "cpu":
        raise ConfigError(
            f"bench={target} runs on the CPU only; drop device={device} (suites with a device: bench=ddp, bench=epoch_time)."
        )
    return {}
