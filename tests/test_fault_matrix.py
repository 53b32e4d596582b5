"""Fault matrix: every bad input ends with one clear message, its documented exit code, and nothing lost or
half-written (issue 12). Also the outcomes that must hold when nothing is wrong: checkpoint exports that never
destroy another run's model, file permissions, `--help` without torch.

Cases run `mpsim.cli.main` in-process (`tests.helpers.run_mpsim`; one subprocess case checks that torch is not
imported). Each case gets a fresh directory to start from; a module workspace holds a trained tiny lorenz3
checkpoint and its run.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shlex
import shutil
import signal
import socket
import stat
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from mpsim.training.checkpoint import save_checkpoint
from tests.helpers import TINY_TRAIN, run_mpsim, run_mpsim_ok

EVAL = ["data.n_test=3", "data.horizon=5", "eval.plots=false"]
NO_TORCH = "import sys; from mpsim.cli import main\n"


def snapshot(*roots: Path) -> dict[Path, tuple[int, int]]:
    """Every file under `roots` with (size, modification time)."""
    return {p: (p.stat().st_size, p.stat().st_mtime_ns) for r in roots for p in r.rglob("*") if p.is_file()}


# ---- shared workspace -----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def ws(tmp_path_factory):
    """A workspace where `mpsim train system=lorenz3` (tiny) has run: checkpoints/lorenz3.ckpt and its run dir."""
    root = tmp_path_factory.mktemp("faults")
    res = run_mpsim(["train", "system=lorenz3", *TINY_TRAIN], root)
    assert res.code == 0, res.err
    assert (root / "checkpoints" / "lorenz3.ckpt").is_file()
    return root


def lorenz_run(ws: Path) -> Path:
    (run_dir,) = (ws / "outputs" / "train").glob("*/*_lorenz3")
    return run_dir


def payload(ws: Path) -> dict:
    """The lorenz3 checkpoint's content (to save altered copies)."""
    return torch.load(ws / "checkpoints" / "lorenz3.ckpt", weights_only=True)


def altered(ws: Path, d: Path, change: Callable[[dict], None], name: str = "bad.ckpt") -> Path:
    """A copy of the lorenz3 checkpoint changed by `change`, saved with a valid checksum."""
    p = payload(ws)
    change(p)
    return save_checkpoint(d / name, p)


# ---- data files ---------------------------------------------------------------------------------------------
def grid_rows(n_traj: int = 4, times=(0.0, 0.1, 0.2, 0.3), nodes: int = 2) -> list[list]:
    return [[b, t, n, 0.1 * n + t + 0.01 * b, -t] for b in range(n_traj) for t in times for n in range(nodes)]


def write_csv(d: Path, rows=None, sidecar: str | None = None, name: str = "m") -> Path:
    path = d / f"{name}.csv"
    pd.DataFrame(rows or grid_rows(), columns=["traj", "t", "node", "theta", "omega"]).to_csv(path, index=False)
    pd.DataFrame([(0, 1), (1, 0)], columns=["src", "dst"]).to_csv(d / f"{name}_edges.csv", index=False)
    if sidecar is not None:
        (d / f"{name}.json").write_text(sidecar)
    return path


def write_npz(d: Path, name: str = "d.npz", **changes) -> Path:
    rng = np.random.default_rng(0)
    arrays = {
        "t": np.arange(6) * 0.1,
        "x": rng.normal(size=(6, 6, 2, 2)),
        "edge_index": np.array([[0, 1], [1, 0]]),
        "meta": np.array(json.dumps({"system": "measured", "state_names": ["theta", "omega"]})),
    }
    arrays.update(changes)
    arrays = {k: v for k, v in arrays.items() if v is not None}
    np.savez(d / name, **arrays)
    return d / name


def data_args(path: Path) -> list[str]:
    return ["train", f"data.path={path}", *TINY_TRAIN[:2], "eval.horizons=[1,5]", "eval.plots=false"]


SPEC = 'states: [x]\nequations:\n  x: "{eq}"\nparams: {{k: 1.0}}\n'


def _spec(d: Path, text: str, *extra: str) -> list[str]:
    """A spec file in `d` and the train command that reads it."""
    (d / "spec.yaml").write_text(text)
    return ["train", "model=equations", f"model.spec={d / 'spec.yaml'}", *extra, *TINY_TRAIN[:2]]


# ---- bounded reading (issue 58): alias bombs, deep nesting, oversized files, named pipes ---------------------
DEEP_JSON = "[" * 100_000 + "]" * 100_000  # used to end in a RecursionError traceback wherever JSON was read
DEEP_YAML = "a: " + "[" * 100_000 + "]" * 100_000 + "\n"


def billion_laughs(levels: int = 9) -> str:
    """A 1.3 KB YAML whose nine levels of anchors and aliases would expand to 9**10 values: as a spec, mpsim ran for
    over 5 minutes at 1.6 GB."""
    lines = [
        "states: [x]",
        'equations: {x: "-k*x"}',
        "params: {k: 1.0}",
        "a0: &a0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]",
    ]
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]" for i in range(1, levels + 1)]
    return "\n".join(lines) + "\n"


def fifo(d: Path, name: str) -> Path:
    """A named pipe at `d/name`: opening it for reading would block until a writer came."""
    os.mkfifo(d / name)
    return d / name


def _report_run(d: Path, record: str, text: str, *extra: str) -> list[str]:
    """A finished run folder whose `record` (summary.json or a .hydra file) holds `text`, and the report of it."""
    run = d / "runs" / "r"
    (run / ".hydra").mkdir(parents=True)
    (run / "summary.json").write_text('{"task": "train", "mode": "scratch"}')
    (run / record).write_text(text)
    return ["report", *extra, f"runs=[{d / 'runs'}]"]


# ---- the cases ------------------------------------------------------------------------------------------------
@dataclass
class Case:
    """`args(ws, d)` builds the command line (and any input files in `d`); the run must end with `code`, one
    `mpsim <cmd>: error:` line containing `match` (for failures), and no file changed, removed, or added
    (outside the dataset cache)."""

    args: Callable[[Path, Path], list[str]]
    code: int
    match: str
    forbid: tuple[str, ...] = ()  # texts the output must not contain
    allow_new: tuple[str, ...] = ("outputs/.cache/",)


def _bytes_flipped(ws: Path, d: Path) -> list[str]:
    """A checkpoint with 4 bytes overwritten inside a weight tensor's stored data."""
    src = (ws / "checkpoints" / "lorenz3.ckpt").read_bytes()
    state = payload(ws)["model"]["state_dict"]
    name = max(state, key=lambda k: state[k].numel())
    raw = state[name].contiguous().numpy().tobytes()
    at = src.find(raw)
    assert at > 0, "weight bytes not found in the file"
    data = bytearray(src)
    data[at + 8 : at + 12] = b"\x7f\x7f\x7f\x7f"
    (d / "flipped.ckpt").write_bytes(bytes(data))
    return ["eval", f"init={d / 'flipped.ckpt'}", "system=lorenz3", *EVAL]


def _malicious(ws: Path, d: Path) -> list[str]:
    effect = payload_effect(d / "pwned.txt")
    altered(ws, d, lambda p: p["model"]["config"].__setitem__("effects", [effect]), "evil.ckpt")
    return ["eval", f"init={d / 'evil.ckpt'}", "system=lorenz3", *EVAL]


def payload_effect(target: Path) -> dict:
    """A config node that writes `target` when `hydra.utils.instantiate` builds it."""
    return {
        "_target_": "pathlib.Path.write_text",
        "self": {"_target_": "pathlib.Path", "_args_": [str(target)]},
        "data": "pwned",
    }


def _os_system(ws: Path, d: Path) -> list[str]:
    def change(p):
        p["model"]["config"] = {"_target_": "os.system", "_args_": [f"touch {d / 'pwned2'}"]}

    altered(ws, d, change, "evil2.ckpt")
    return ["eval", f"init={d / 'evil2.ckpt'}", "system=lorenz3", *EVAL]


def _no_state_dim(ws, d):
    return ["eval", f"init={altered(ws, d, lambda p: p['model'].pop('state_dim'))}", "system=lorenz3", *EVAL]


def _nan_weight(ws, d):
    def change(p):
        first = next(iter(p["model"]["state_dict"]))
        p["model"]["state_dict"][first].view(-1)[0] = float("nan")

    return ["eval", f"init={altered(ws, d, change)}", "system=lorenz3", *EVAL]


def _resume_other_lr(ws, d):
    return ["train", f"resume={lorenz_run(ws)}", "trainer.lr=0.5"]


def _resume_damaged_state(ws: Path, d: Path) -> list[str]:
    """A copy of the trained run whose last.ckpt counts its epochs with a word (saved with a valid checksum)."""
    run_dir = d / "run"
    shutil.copytree(lorenz_run(ws), run_dir)
    last = run_dir / "checkpoints" / "last.ckpt"
    p = torch.load(last, weights_only=True)
    p["trainer"]["epoch"] = "many"
    save_checkpoint(last, p)
    return ["train", f"resume={run_dir}"]


def _resume_fewer_epochs(ws: Path, d: Path) -> list[str]:
    run_dir = d / "run"
    shutil.copytree(lorenz_run(ws), run_dir)
    return ["train", f"resume={run_dir}", "trainer.max_epochs=1"]


def _resume_damaged_record(ws: Path, d: Path, text: str) -> list[str]:
    """A copy of the trained run whose `.hydra/overrides.yaml` is not the list of overrides Hydra wrote."""
    run_dir = d / "run"
    shutil.copytree(lorenz_run(ws), run_dir)
    (run_dir / ".hydra" / "overrides.yaml").write_text(text)
    return ["train", f"resume={run_dir}"]


def _replace_export(ws, d):
    (d / "checkpoints").mkdir()
    shutil.copy(ws / "checkpoints" / "lorenz3.ckpt", d / "checkpoints" / "pendulum2.ckpt")
    return ["train", *TINY_TRAIN, "eval.plots=false"]


def _damaged_metrics(ws: Path, d: Path, text: str) -> list[str]:
    """A copy of the trained run whose metrics.csv is not the table a trainer writes, drawn by layout=curves."""
    shutil.copytree(lorenz_run(ws), d / "runs" / "r")
    (d / "runs" / "r" / "metrics.csv").write_text(text)
    return ["report", "layout=curves", f"runs=[{d / 'runs'}]"]


def _damaged_history(p: dict) -> None:
    """A trainer state whose history rows are longer than its columns."""
    p["trainer"] = {"history_json": '{"columns": ["epoch"], "rows": [[1, 2]]}'}


def _nan_data_into(d: Path, folder: str, *files: str) -> list[str]:
    """A folder of the user's holding `files`, and a train run pointed at it whose data file holds a NaN."""
    (d / folder).mkdir()
    for name in files:
        (d / folder / name).write_text(f"the user's own {name}\n")
    x = np.random.default_rng(0).normal(size=(6, 6, 2, 2))
    x[0, 0, 0, 0] = np.nan
    return [*data_args(write_npz(d, x=x)), f"hydra.run.dir={folder}"]


def _into_a_run(ws: Path, d: Path, command: list[str]) -> list[str]:
    """A copy of the trained lorenz3 run, and `command` pointed at its folder."""
    shutil.copytree(lorenz_run(ws), d / "run")
    return [*command, f"hydra.run.dir={d / 'run'}"]


def _fake_sweep(d: Path) -> Path:
    """A folder holding an earlier sweep: Hydra's multirun.yaml and one job's record."""
    (d / "sweep" / "0" / ".hydra").mkdir(parents=True)
    (d / "sweep" / "multirun.yaml").write_text("hydra: {}\n")
    (d / "sweep" / "0" / ".hydra" / "overrides.yaml").write_text("- seed=0\n")
    return d / "sweep"


CASES: dict[str, Case] = {
    # -- config: typos get a did-you-mean in every group, never Hydra's "+key" advice
    "typo_system_key": Case(lambda w, d: ["train", "system.n_node=4"], 2, "Did you mean system.n_nodes?", ("+system",)),
    "typo_trainer_key": Case(lambda w, d: ["train", "trainer.lrr=1"], 2, "Did you mean trainer.lr?", ("+trainer",)),
    "typo_data_key": Case(lambda w, d: ["train", "data.n_tran=5"], 2, "Did you mean data.n_train", ("+data",)),
    "typo_eval_key": Case(lambda w, d: ["eval", "init=x", "eval.horizon=[1]"], 2, "Did you mean eval.horizons?"),
    "typo_paths_key": Case(lambda w, d: ["train", "paths.ckpt_di=x"], 2, "Did you mean paths.ckpt_dir?"),
    "typo_mode_key": Case(lambda w, d: ["train", "mode.nam=x"], 2, "Did you mean mode.name?"),
    "typo_group": Case(lambda w, d: ["train", "traner.lr=1"], 2, "Did you mean trainer?"),
    "typo_report_key": Case(lambda w, d: ["report", "titl=x"], 2, "Did you mean title?"),
    "typo_model_param": Case(lambda w, d: ["train", "model.hiden=8"], 2, "Did you mean model.hidden"),
    "param_not_in_yaml": Case(lambda w, d: ["train", "system=nbody", "system.mass=2"], 2, "+system.mass=<value>"),
    "unknown_system": Case(lambda w, d: ["train", "system=lorenz4"], 2, "Could not find 'system/lorenz4'"),
    "unknown_model": Case(lambda w, d: ["train", "model=mpnod"], 2, "Could not find 'model/mpnod'"),
    "wrong_type": Case(lambda w, d: ["train", "trainer.max_epochs=many"], 2, "could not be converted to Integer"),
    "wrong_type_target": Case(
        lambda w, d: ["train", "system=lorenz3", "system.coupling=strong", *TINY_TRAIN], 2, "expects float"
    ),
    "device_tpu": Case(lambda w, d: ["train", "device=tpu"], 2, "device=tpu is not supported"),
    "threads_negative": Case(lambda w, d: ["train", "threads=-2"], 2, "threads=-2"),
    "sigma_nan": Case(
        lambda w, d: ["train", "system=lorenz3", "system.sigma=nan"], 2, "system.sigma=nan is not a finite number"
    ),
    "noise_negative": Case(lambda w, d: ["train", "data.noise_std=-1"], 2, "data.noise_std=-1.0"),
    "patience_negative": Case(
        lambda w, d: ["train", "trainer.early_stop_patience=-1"], 2, "trainer.early_stop_patience=-1"
    ),
    "lr_zero": Case(lambda w, d: ["train", "trainer.lr=0"], 2, "trainer.lr=0.0: must be > 0"),
    "horizon_zero": Case(lambda w, d: ["train", "eval.horizons=[0,5]"], 2, "eval.horizons=[0, 5]"),
    "horizon_beyond_record": Case(
        lambda w, d: ["train", *TINY_TRAIN[:-1], "eval.horizons=[1,5,50]"], 2, "[50] go beyond the record"
    ),
    "simulate_n_zero": Case(lambda w, d: ["simulate", "n=0"], 2, "n=0"),
    "simulate_training_seed": Case(lambda w, d: ["simulate", "n=2", "seed=7"], 2, "Pass data.seed=7 instead"),
    "noise_overflow": Case(lambda w, d: ["train", *TINY_TRAIN, "data.noise_std=1e40"], 2, "data.noise_std=1e+40"),
    "smnn_record_shorter_than_context": Case(
        lambda w, d: ["train", "model=smnn_forecast", *TINY_TRAIN[:-1], "data.horizon=2"], 2, "use data.horizon >= 10"
    ),
    "simulate_blowup": Case(  # the ground truth cannot be integrated at these parameters (train shares the path)
        lambda w, d: ["simulate", "system=lorenz3", "n=2", "data.horizon=5", "system.sigma=1e300"],
        2,
        "cannot simulate CoupledLorenz",
    ),
    "solver_step_too_small": Case(  # torchdiffeq's fixed grid for 1e-12 was a 20 TB allocation ("out of memory")
        lambda w, d: ["train", *TINY_TRAIN, "solver=rk4", "solver.step_size=1e-12"],
        2,
        "solver.step_size=1e-12 needs 1e+11 rk4 steps",
    ),
    "simulate_dt_far_too_long": Case(  # a fixed-step ground truth (velocity Verlet) would take 8e8 steps: it hung
        lambda w, d: ["simulate", "system=nbody20", "n=2", "data.horizon=2", "data.dt=1e6"],
        2,
        "cannot simulate nbody20: one sampling interval of 1e+06 needs 8e+08 integrator steps",
    ),
    "sweep_interval_without_search": Case(  # Hydra's BasicSweeper traceback ("does not support sweep type")
        lambda w, d: ["train", "-m", *TINY_TRAIN, "trainer.lr=interval(1e-3,1e-2)"], 2, "an interval is a search space"
    ),
    "device_mps_missing": Case(lambda w, d: ["train", *TINY_TRAIN, "device=mps"], 2, "device=mps but Apple's MPS"),
    "sweep_bad_value": Case(lambda w, d: ["train", "-m", *TINY_TRAIN, "data.n_train=4,-1"], 2, "data.n_train=-1"),
    "unknown_command": Case(lambda w, d: ["frobnicate"], 2, "unknown command 'frobnicate'"),
    # -- output locations that cannot be written: refused before any work
    "output_root_unwritable": Case(
        lambda w, d: ((d / "f").write_text("x"), ["train", f"paths.output_root={d}/f/o"])[1],
        4,
        "is a file, not a directory",
    ),
    "ckpt_dir_unwritable": Case(
        lambda w, d: ((d / "f").write_text("x"), ["train", f"paths.ckpt_dir={d}/f/c"])[1], 4, "paths.ckpt_dir="
    ),
    # -- resume
    "resume_missing_dir": Case(lambda w, d: ["train", f"resume={d}/nowhere"], 2, "last.ckpt does not exist"),
    "resume_other_lr": Case(_resume_other_lr, 2, "trainer.lr=0.5 (not set in the run)"),
    "resume_fewer_epochs": Case(_resume_fewer_epochs, 2, "has already run 3 epochs; trainer.max_epochs=1 is fewer"),
    "resume_damaged_state": Case(_resume_damaged_state, 2, "'trainer.epoch' is 'many'"),
    "resume_overrides_python_tag": Case(
        lambda w, d: _resume_damaged_record(w, d, "!!python/object/apply:os.system ['touch pwned.txt']\n"),
        2,
        "run/.hydra/overrides.yaml is not valid YAML",
    ),
    "resume_overrides_not_a_list": Case(
        lambda w, d: _resume_damaged_record(w, d, "{seed: 0}\n"),
        2,
        "run/.hydra/overrides.yaml must be a list of key=value overrides; got dict",
    ),
    "resume_true_no_run": Case(lambda w, d: ["train", "resume=true", "seed=7"], 2, "no earlier run"),
    # -- checkpoints: data, never code
    "init_missing": Case(lambda w, d: ["eval", "init=nowhere.ckpt", "system=lorenz3", *EVAL], 2, "no such checkpoint"),
    "ckpt_empty": Case(
        lambda w, d: ((d / "e.ckpt").write_bytes(b""), ["eval", f"init={d / 'e.ckpt'}", *EVAL])[1],
        2,
        "is empty (0 bytes)",
    ),
    "ckpt_truncated": Case(
        lambda w, d: (
            (d / "t.ckpt").write_bytes((w / "checkpoints/lorenz3.ckpt").read_bytes()[:300]),
            ["eval", f"init={d / 't.ckpt'}", *EVAL],
        )[1],
        2,
        "cannot read checkpoint",
    ),
    "ckpt_foreign": Case(
        lambda w, d: (torch.save({"w": torch.zeros(2)}, d / "f.ckpt"), ["eval", f"init={d / 'f.ckpt'}", *EVAL])[1],
        2,
        "not an mpsim checkpoint",
    ),
    "ckpt_no_state_dim": Case(_no_state_dim, 2, "lacks 'model.state_dim'"),
    "ckpt_bytes_flipped": Case(_bytes_flipped, 2, "does not match the checksum"),
    "ckpt_nan_weight": Case(_nan_weight, 2, "holds NaN/inf"),
    "ckpt_history_damaged": Case(  # a last.ckpt's metric history that is not the table a trainer writes
        lambda w, d: ["eval", f"init={altered(w, d, _damaged_history)}", *EVAL],
        2,
        "'trainer.history_json' is not the table of metric rows",
    ),
    "ckpt_malicious_effect": Case(_malicious, 2, "'pathlib.Path.write_text' is not an mpsim class"),
    "ckpt_os_system": Case(_os_system, 2, "'os.system' is not an mpsim class"),
    "ckpt_mpsim_function": Case(
        lambda w, d: [
            "eval",
            f"init={altered(w, d, lambda p: p['model']['config'].__setitem__('effects', [{'_target_': 'mpsim.files.atomic_write', 'path': str(d / 'x'), 'write': None}]))}",
            *EVAL,
        ],
        2,
        "'mpsim.files.atomic_write' is not an mpsim class",
    ),
    "ckpt_interpolation": Case(
        lambda w, d: [
            "eval",
            f"init={altered(w, d, lambda p: p['model']['config'].__setitem__('aggregation', '${oc.env:HOME}'))}",
            *EVAL,
        ],
        2,
        "holds an interpolation",
    ),
    "ckpt_newer": Case(
        lambda w, d: ["eval", f"init={altered(w, d, lambda p: p.__setitem__('version', 99))}", *EVAL], 2, "newer mpsim"
    ),
    "ckpt_other_system": Case(
        lambda w, d: ["eval", f"init={w / 'checkpoints/lorenz3.ckpt'}", "system=pendulum2", *EVAL],
        2,
        "was trained on lorenz3",
    ),
    # -- data files
    "csv_empty_traj": Case(
        lambda w, d: data_args(
            write_csv(
                d, [[None if i == 5 and j == 0 else v for j, v in enumerate(r)] for i, r in enumerate(grid_rows())]
            )
        ),
        2,
        "row 7, column 'traj' is empty",
    ),
    "csv_nan_value": Case(
        lambda w, d: data_args(
            write_csv(d, [[*r[:3], float("nan") if i == 2 else r[3], r[4]] for i, r in enumerate(grid_rows())])
        ),
        2,
        "row 4, column 'theta' is empty",
    ),
    "csv_ragged": Case(lambda w, d: data_args(write_csv(d, grid_rows()[:-1])), 2, "ragged data"),
    "csv_sidecar_malformed": Case(lambda w, d: data_args(write_csv(d, sidecar="{not json")), 2, "m.json: the metadata"),
    "csv_sidecar_list": Case(lambda w, d: data_args(write_csv(d, sidecar="[1, 2]")), 2, "m.json must be a JSON object"),
    "csv_sidecar_wrong_type": Case(
        lambda w, d: data_args(write_csv(d, sidecar='{"control_columns": "omega"}')),
        2,
        "key 'control_columns' must be a list",
    ),
    "npz_meta_list": Case(
        lambda w, d: data_args(write_npz(d, meta=np.array("[1, 2]"))), 2, "array 'meta' must be a JSON object"
    ),
    "npz_float_edge_ids": Case(
        lambda w, d: data_args(write_npz(d, edge_index=np.array([[0.0, 1.5], [1.0, 0.0]]))), 2, "node id 1.5"
    ),
    "npz_complex_states": Case(
        lambda w, d: data_args(write_npz(d, x=np.ones((6, 6, 2, 2)) * (1 + 1j))), 2, "array 'x' is complex"
    ),
    "npz_zero_nodes": Case(
        lambda w, d: data_args(write_npz(d, x=np.ones((6, 6, 0, 2)), edge_index=np.zeros((2, 0), dtype=int))),
        2,
        "zero nodes (N)",
        ("diverged",),
    ),
    "npz_float32_overflow": Case(
        lambda w, d: data_args(write_npz(d, x=np.full((6, 6, 2, 2), 1e300))), 2, "overflow float32", ("NaN",)
    ),
    "npz_missing_x": Case(lambda w, d: data_args(write_npz(d, x=None)), 2, "missing array(s) ['x']"),
    "data_missing_file": Case(lambda w, d: data_args(d / "nothing.npz"), 2, "does not exist"),
    "data_path_folder": Case(lambda w, d: ((d / "runs.npz").mkdir(), data_args(d / "runs.npz"))[1], 2, "is a folder"),
    "data_unknown_format": Case(
        lambda w, d: ((d / "d.xlsx").write_text("1"), data_args(d / "d.xlsx"))[1], 2, "unknown data format '.xlsx'"
    ),
    # -- report
    "report_metrics_text": Case(
        lambda w, d: _damaged_metrics(w, d, "epoch,test_error\n1,abc\n"), 2, "holds 'abc' in row 2"
    ),
    "report_metrics_columns": Case(lambda w, d: _damaged_metrics(w, d, "a,b\n1,2\n"), 2, "has no epoch or test_error"),
    "report_corrupt_summary": Case(
        lambda w, d: (
            (d / "runs/a").mkdir(parents=True),
            (d / "runs/a/summary.json").write_text('{"task": "tr'),
            ["report", f"runs=[{d / 'runs'}]"],
        )[2],
        2,
        "runs/a/summary.json is not valid JSON",
    ),
    "report_summary_list": Case(
        lambda w, d: (
            (d / "runs/b").mkdir(parents=True),
            (d / "runs/b/summary.json").write_text("[1]"),
            ["report", f"runs=[{d / 'runs'}]"],
        )[2],
        2,
        "runs/b/summary.json must hold a JSON object",
    ),
    "report_layout_config_python_tag": Case(
        lambda w, d: (
            (d / "runs/c/.hydra").mkdir(parents=True),
            (d / "runs/c/summary.json").write_text('{"task": "train", "mode": "scratch"}'),
            (d / "runs/c/.hydra/config.yaml").write_text("!!python/object/apply:os.system ['touch pwned.txt']\n"),
            ["report", "layout=table2", f"runs=[{d / 'runs'}]"],
        )[3],
        2,
        "runs/c/.hydra/config.yaml is not valid YAML",
    ),
    "report_overrides_python_tag": Case(
        lambda w, d: (
            (d / "runs/o/.hydra").mkdir(parents=True),
            (d / "runs/o/summary.json").write_text('{"task": "train", "mode": "scratch"}'),
            (d / "runs/o/.hydra/overrides.yaml").write_text("!!python/object/apply:os.system ['touch pwned.txt']\n"),
            ["report", f"runs=[{d / 'runs'}]"],
        )[3],
        2,
        "runs/o/.hydra/overrides.yaml is not valid YAML",
    ),
    "report_missing_path": Case(
        lambda w, d: (
            (d / "runs/a").mkdir(parents=True),
            (d / "runs/a/summary.json").write_text("{}"),
            ["report", f"runs=[{d / 'runs'},{d / 'rusn'}]"],
        )[2],
        2,
        "rusn' matches no file or folder",
    ),
    "report_nothing_finished": Case(
        lambda w, d: ((d / "runs/a").mkdir(parents=True), ["report", f"runs=[{d / 'runs'}]"])[1],
        2,
        "no run there has finished",
    ),
    # -- memory: estimated and refused before anything is allocated
    "memory_simulate_nbody": Case(
        lambda w, d: ["simulate", "system=nbody", "system.n_particles=10000000"], 5, "memory_check=false"
    ),
    "memory_train_nbody": Case(
        lambda w, d: ["train", "system=nbody", "system.n_particles=10000000", "model=deltagn"], 5, "is available on cpu"
    ),
    # -- equation specs (model=equations / system=equations): data, never code
    "spec_missing": Case(
        lambda w, d: ["train", "model=equations", f"model.spec={d / 'none.yaml'}"], 2, "does not exist"
    ),
    "spec_python_tag": Case(
        lambda w, d: _spec(d, "!!python/object/apply:os.system ['touch pwned.txt']\n"), 2, "cannot read spec file"
    ),
    "spec_code_in_equation": Case(
        lambda w, d: _spec(d, SPEC.format(eq="__import__('os').system('touch pwned.txt')")),
        2,
        "only plain function names can be called",
    ),
    "spec_unknown_name": Case(lambda w, d: _spec(d, SPEC.format(eq="-kk*x")), 2, "Did you mean 'k'"),
    "spec_wrong_states": Case(lambda w, d: _spec(d, SPEC.format(eq="-k*x"), "system=lorenz3"), 2, "has 1 states"),
    # a power of constants is computed exactly when it is read: 9**9**9**9 used to hang mpsim, taking all memory
    "spec_power_tower": Case(lambda w, d: _spec(d, SPEC.format(eq="-k*x*9**9**9**9")), 2, "beyond float64"),
    "spec_infinite_constant": Case(
        lambda w, d: (
            (d / "sys.yaml").write_text(SPEC.format(eq="-k*x*1e309") + "nodes: 2\ngraph: chain\n"),
            ["simulate", "system=equations", f"system.spec={d / 'sys.yaml'}", "n=2"],
        )[1],
        2,
        "system.spec.equations.x: -oo is not a finite real number",
    ),
    "spec_huge_graph": Case(  # used to end in a MemoryError traceback while building the graph
        lambda w, d: (
            (d / "sys.yaml").write_text(SPEC.format(eq="-k*x") + "nodes: 100000000000\ngraph: chain\n"),
            ["simulate", "system=equations", f"system.spec={d / 'sys.yaml'}", "n=2"],
        )[1],
        5,
        "a chain graph on 100000000000 nodes needs about",
    ),
    # -- model sizes from a checkpoint or the config: checked on the meta device before anything is allocated
    "ckpt_config_declares_other_sizes": Case(
        lambda w, d: ["eval", f"init={_declaring(w, d, hidden=3000)}", "system=lorenz3", *EVAL],
        2,
        "bad.ckpt: its model.config does not describe its weights: model.state_dict['net.0.weight'] is [32, 6] but "
        "the config builds [3000, 6]",
    ),
    "ckpt_override_too_large": Case(  # used to try to allocate 4 TB, then 'cannot build model ... can't allocate'
        lambda w, d: [
            "eval",
            f"init={w / 'checkpoints/lorenz3.ckpt'}",
            "system=lorenz3",
            "model.hidden=1000000",
            *EVAL,
        ],
        2,
        "does not fit this model (model.hidden: checkpoint 32, config 1000000)",
    ),
    "memory_model_weights": Case(
        lambda w, d: ["train", "system=lorenz3", "model.hidden=1000000", *TINY_TRAIN],
        5,
        "1,000,014,000,006 weights with their gradients and optimiser state",
    ),
    # -- run folders (issue 58): a failed command removes only what it made; a folder holding a run is not reused;
    # an output location that cannot be created names the key to change
    "run_folder_of_logs_survives_a_bad_input": Case(  # the folder and its log were deleted (harmful)
        lambda w, d: _nan_data_into(d, "mylogs", "server.log"), 2, "`x` has NaN/inf"
    ),
    "run_folder_populated_keeps_no_record_of_a_bad_input": Case(  # .hydra/ was left there, train.log appended
        lambda w, d: _nan_data_into(d, "mine", "notes.txt", "train.log"), 2, "`x` has NaN/inf"
    ),
    "run_folder_holding_a_run_is_refused": Case(  # trained over the run: best.ckpt replaced, no backup (harmful)
        lambda w, d: _into_a_run(w, d, ["train", "system=lorenz3", *TINY_TRAIN]),
        2,
        "already holds a run (.hydra); nothing was written. Continue it with resume=",
    ),
    "run_folder_holding_a_run_is_refused_by_simulate": Case(
        lambda w, d: _into_a_run(w, d, ["simulate", "system=lorenz3", "n=2", "data.horizon=3"]),
        2,
        "or add overwrite=true to move its files to",
    ),
    "sweep_folder_holding_a_sweep_is_refused": Case(
        lambda w, d: ["train", "-m", *TINY_TRAIN, "seed=0,1", f"hydra.sweep.dir={_fake_sweep(d)}"],
        2,
        "already holds a sweep (multirun.yaml)",
    ),
    "run_dir_uncreatable": Case(  # FileNotFoundError traceback, exit 1
        lambda w, d: ["train", "hydra.run.dir=/proc/x"], 4, "hydra.run.dir=/proc/x: cannot create /proc/x"
    ),
    "run_dir_under_a_file": Case(
        lambda w, d: ((d / "f").write_text("x"), ["train", f"hydra.run.dir={d}/f/x"])[1], 4, "is a file, not a dir"
    ),
    "output_root_uncreatable": Case(
        lambda w, d: ["train", "paths.output_root=/proc/x"],
        4,
        "/proc is not writable (permissions, or a read-only or virtual",
    ),
    "sweep_dir_uncreatable": Case(
        lambda w, d: ["train", "-m", *TINY_TRAIN, "seed=0,1", "hydra.sweep.dir=/proc/s"],
        4,
        "hydra.sweep.dir=/proc/s: cannot create /proc/s",
    ),
    # -- bounded reading (issue 58): every YAML and JSON file within size, depth and alias limits; named pipes and
    # values beyond the model's precision named for what they are. The billion-laughs spec: its own test below.
    "spec_deep_nesting": Case(lambda w, d: _spec(d, SPEC.format(eq="-k*x") + DEEP_YAML), 2, "nest more than 64 levels"),
    "spec_too_large": Case(
        lambda w, d: _spec(d, SPEC.format(eq="-k*x") + ("# padding\n" * 120_000)),
        2,
        "spec.yaml is 1.14 MB, over mpsim's limit of 1 MB",
    ),
    "spec_fifo": Case(
        lambda w, d: ["train", "model=equations", f"model.spec={fifo(d, 'spec.yaml')}"], 2, "is a named pipe (FIFO)"
    ),
    "npz_meta_deep": Case(
        lambda w, d: data_args(write_npz(d, meta=np.array(DEEP_JSON))),
        2,
        "array 'meta' nests lists or objects 100,000 levels deep, over mpsim's limit of 64",
    ),
    "csv_sidecar_deep": Case(
        lambda w, d: data_args(write_csv(d, sidecar='{"a": ' * 100_000 + "1" + "}" * 100_000)),
        2,
        "m.json: the metadata file beside the CSV nests lists or objects 100,000 levels deep",
    ),
    "csv_sidecar_too_large": Case(
        lambda w, d: data_args(write_csv(d, sidecar='{"pad": "' + "x" * (9 << 20) + '"}')),
        2,
        "m.json: the metadata file beside the CSV is 9 MB, over mpsim's limit of 8 MB",
    ),
    "csv_sidecar_fifo": Case(
        lambda w, d: (write_csv(d), fifo(d, "m.json"), data_args(d / "m.csv"))[2],
        2,
        "m.json: the metadata file beside the CSV is a named pipe (FIFO)",
    ),
    "report_summary_deep": Case(
        lambda w, d: _report_run(d, "summary.json", DEEP_JSON), 2, "summary.json nests lists or objects 100,000 levels"
    ),
    "report_overrides_alias_bomb": Case(
        lambda w, d: _report_run(d, ".hydra/overrides.yaml", billion_laughs()),
        2,
        "overrides.yaml: its anchors and aliases (&name, *name) repeat more than 10,000 values",
    ),
    "report_layout_config_deep": Case(
        lambda w, d: _report_run(d, ".hydra/config.yaml", DEEP_YAML, "layout=table2"),
        2,
        "config.yaml: lists or mappings nest more than 64 levels deep",
    ),
    "npz_huge_times": Case(  # was "trajectories: `t` contains NaN or inf", naming no file
        lambda w, d: data_args(write_npz(d, t=np.linspace(0.0, 5e300, 6))),
        2,
        "d.npz: `t` runs from 0.0 to 5e+300: values this large overflow float32",
        ("NaN",),
    ),
    "npz_times_tied_in_float32": Case(
        lambda w, d: data_args(write_npz(d, t=1e10 + 0.01 * np.arange(6))),
        2,
        "t[0] = 10000000000.0 and t[1] = 10000000000.01 are the same number in float32",
    ),
    "csv_inf_value": Case(  # was "holds np.float64(inf)"
        lambda w, d: data_args(
            write_csv(d, [[*r[:3], float("inf") if i == 2 else r[3], r[4]] for i, r in enumerate(grid_rows())])
        ),
        2,
        "row 4, column 'theta' holds inf (not a finite number",
        ("np.float64",),
    ),
    "init_fifo": Case(  # was "no such checkpoint"
        lambda w, d: ["eval", f"init={fifo(d, 'm.ckpt')}", "system=lorenz3", *EVAL],
        2,
        "m.ckpt is a named pipe (FIFO), not a regular file; point init= at a checkpoint file",
    ),
    "data_fifo": Case(lambda w, d: data_args(fifo(d, "d.npz")), 2, "d.npz is a named pipe (FIFO), not a regular file"),
    "data_edges_fifo": Case(
        lambda w, d: [*data_args(write_npz(d)), f"data.edges={fifo(d, 'e.csv')}"], 2, "e.csv is a named pipe (FIFO)"
    ),
    # -- issue 58, Hydra's own ways in: -m hydra/sweeper=optuna as Hydra documents it, trainer.log_every
    "optuna_sweeper_bad_interval": Case(  # was "direction=Direction.minimize: must be minimize or maximize"
        lambda w, d: ["train", "-m", "hydra/sweeper=optuna", "trainer.lr=interval(1e-2,1e-3)"],
        2,
        "the low end must not exceed the high end",
        ("Direction.minimize",),
    ),
    "optuna_sweeper_two_directions": Case(  # was a traceback from the sweeper after the first trial had run
        lambda w, d: [
            "train",
            "-m",
            "hydra/sweeper=optuna",
            "hydra.sweeper.n_trials=1",
            "hydra.sweeper.direction=[minimize,maximize]",
            "trainer.lr=interval(1e-3,1e-2)",
            *TINY_TRAIN,
            "eval.plots=false",
        ],
        2,
        "one direction per objective",
    ),
    "sweeper_params_key_on_the_command_line": Case(  # was Hydra's AssertionError traceback, exit 1
        lambda w, d: ["train", "hydra.sweeper.params.x=1"], 2, "a search space is given on the key itself"
    ),
    "log_every_negative": Case(lambda w, d: ["train", "trainer.log_every=-1"], 2, "trainer.log_every=-1: must be >= 0"),
    # -- issue 60, driven specs: `inputs:` in model=equations / system=equations, the twin's `system.input`
    "driven_twin_without_a_signal": Case(
        lambda w, d: _driven(d, "simulate", "n=2"), 2, "declares the inputs ['u'] but no signal drives them"
    ),
    "driven_twin_input_file_missing": Case(
        lambda w, d: _driven(d, "simulate", "n=2", f"system.input={{file: '{d / 'none.csv'}', column: u}}"),
        2,
        "none.csv does not exist",
    ),
    "driven_twin_input_file_too_short": Case(
        lambda w, d: (
            (d / "u.csv").write_text("t,u\n0,1\n0.5,2\n"),
            _driven(d, "simulate", "n=2", f"system.input={{file: '{d / 'u.csv'}'}}"),
        )[1],
        2,
        "covers t = 0 to 0.5 but the simulation runs from 0 to 1",
    ),
    "driven_model_on_data_without_controls": Case(
        lambda w, d: [
            "train",
            "system=equations",
            "system.spec={states: [x, v], equations: {x: v, v: -x}, nodes: 1}",
            "model=equations",
            f"model.spec={_driven(d, 'train')[2].split('=', 1)[1]}",
            *TINY_TRAIN[:2],
        ],
        2,
        "model.spec.inputs ['u'] are 1 per node but the data have 0 control(s). Map the file's columns",
    ),
    # -- issue 60, recordings as they come: wide CSV / .mat files, a glob, data.columns, data.observed, data.segment
    "recordings_glob_matches_nothing": Case(
        lambda w, d: _recording(d, f"data.path={d / 'rec' / '*.csv'}"), 2, "the pattern matches no file"
    ),
    "recording_column_missing": Case(lambda w, d: _recording(d, "data.columns={q: position}"), 2, "position"),
    "recording_columns_not_a_mapping": Case(lambda w, d: _recording(d, "data.columns=[q]"), 2, "data.columns must map"),
    "recording_not_uniform": Case(lambda w, d: _recording(d, jitter=0.3), 2, "the sampling is not uniform"),
    "recording_segment_too_long": Case(
        lambda w, d: _recording(d, "data.segment=100"), 2, "longer than every recording"
    ),
    "recording_bad_input_hold": Case(
        lambda w, d: _recording(d, "data.input_hold=cubic"), 2, "data.input_hold must be one of"
    ),
    # -- issue 69: the file named, the columns meant, every sample accounted for; one message in the file's terms
    "recording_column_key_typo": Case(  # Q for q: the file's q column (other units) was read, unseen
        lambda w, d: _recording(d, "data.columns={Q: q_rad}"), 2, "'Q' is not a state or input of the model"
    ),
    "recording_column_key_left_out_of_observed": Case(
        lambda w, d: _recording(d, "data.columns={v: vel}"), 2, "data.observed=['q'] leaves 'v' out"
    ),
    "recording_observed_not_a_state": Case(  # used to be refused in internal terms once the run folder existed
        lambda w, d: _recording(d, "data.observed=[q,w]"), 2, "data.observed=[q, w]: 'w' is not a state of the model"
    ),
    "recording_control_not_an_input": Case(
        lambda w, d: _recording(d, "data.control_columns=[tau]"), 2, "'tau' is not an input of the model"
    ),
    "recording_dt_beside_a_time_column": Case(  # data.dt ignored the file's 'time' column and its 2 s gap
        lambda w, d: _recording(d, "data.dt=0.1", header="time,q,u", gap=True), 2, "column 'time' looks like"
    ),
    "recording_copies_in_a_pattern": Case(  # two identical files put copies of training segments into the test
        lambda w, d: _recording(d, f"data.path={d / 'rec*.csv'}", copy=True), 2, "holds the same samples as"
    ),
    "recording_time_with_a_unit": Case(
        lambda w, d: _recording(d, edit=lambda rows: _cell(rows, 5, 0, "0.5s")), 2, "a number with a unit"
    ),
    "recording_footer": Case(lambda w, d: _recording(d, edit=lambda rows: [*rows, "end of record,,"]), 2, "a footer"),
    "recording_header_repeated": Case(
        lambda w, d: _recording(d, edit=lambda rows: [*rows[:100], "t,q,u", *rows[100:]]), 2, "repeats the header"
    ),
    "recording_path_mistyped": Case(
        lambda w, d: _recording(d, f"data.path={d / 'recc.csv'}"), 2, "does not exist (data.path). Did you mean"
    ),
    "recording_path_a_folder": Case(lambda w, d: _recording(d, f"data.path={d}"), 2, "is a folder"),
    "recording_segment_not_whole_steps": Case(
        lambda w, d: _recording(d, "data.segment=0.123"), 2, "Use data.segment=0.1 or data.segment=0.2"
    ),
    "recording_stride_changes_the_segment": Case(
        lambda w, d: _recording(d, "data.stride=15"), 2, "0.6667 steps of 1.5 s after data.stride=15"
    ),
    "recording_segment_1e308": Case(  # an OverflowError traceback
        lambda w, d: _recording(d, "data.segment=1e308"), 2, "longer than every recording"
    ),
    "recording_input_sample_1e30": Case(  # a ZeroDivisionError traceback in dopri5's first step
        lambda w, d: _recording(d, edit=lambda rows: _cell(rows, 57, 2, "1e30")), 2, "row 58 (line 59), column 'u'"
    ),
    "recording_beyond_float32": Case(  # was "x[8, 10, 0, 0] = ...": a batch index, not the file's row
        lambda w, d: _recording(d, edit=lambda rows: _cell(rows, 90, 1, "1e39")), 2, "row 91 (line 92), column 'q'"
    ),
    "recording_resample_zero": Case(lambda w, d: _recording(d, "data.resample=0"), 2, "data.resample=0.0: give a step"),
    "recording_columns_unquoted_text": Case(  # a bare Hydra lexer exception
        lambda w, d: _recording(d, "data.columns={q: θ pos}"), 2, """'data.columns={q: "θ pos"}'"""
    ),
    "recording_path_with_brackets_unquoted": Case(
        lambda w, d: _recording(d, f"data.path={d / 'rec[1].csv'}"), 2, "quote the value inside the single quotes"
    ),
    "recordings_too_few_without_segments": Case(  # said "use a shorter data.segment" though none was given
        lambda w, d: _recording(d, "data.segment=null"), 2, "1 recordings cannot be split"
    ),
    "batch_file_inputs_read_as_states": Case(  # said "the data have 0 control(s)" though the file has column u
        lambda w, d: _long_driven(d), 2, "read as states because data.control_columns does not list them"
    ),
    "recording_keys_on_a_batch_file": Case(
        lambda w, d: (
            (d / "long.csv").write_text("traj,t,node,x\n0,0,0,1\n0,1,0,2\n1,0,0,1\n1,1,0,2\n2,0,0,1\n2,1,0,2\n"),
            ["train", f"data.path={d / 'long.csv'}", "data.stride=2", *TINY_TRAIN[:2]],
        )[1],
        2,
        "data.stride apply to recordings",
    ),
}

RECORDING_SPEC = "states: [q, v]\ninputs: [u]\nequations: {q: v, v: -k*q + u}\nparams: {k: 4.0}\n"


def _recording(
    d: Path,
    *extra: str,
    jitter: float = 0.0,
    header: str = "t,q,u",
    gap: bool = False,
    copy: bool = False,
    edit: Callable[[list[str]], list[str]] | None = None,
) -> list[str]:
    """A wide CSV of one recording (t, q, u; 30 s at 10 Hz, times moved by `jitter` of a step on every third
    sample; with `gap`, 2 s missing after 10 s; its rows changed by `edit`; with `copy`, also as rec2.csv) and the
    `mpsim train` of a driven spec on it, positions only, in 1 s segments."""
    t = [0.1 * k + (0.1 * jitter if k % 3 == 1 else 0.0) + (2.0 if gap and k > 100 else 0.0) for k in range(301)]
    rows = [f"{tk:.4f},{0.01 * k},{(k % 7) / 7}" for k, tk in enumerate(t)]
    rows = edit(rows) if edit is not None else rows
    (d / "rec.csv").write_text(header + "\n" + "\n".join(rows) + "\n")
    if copy:
        shutil.copy(d / "rec.csv", d / "rec2.csv")
    (d / "rec.yaml").write_text(RECORDING_SPEC)
    keys = [f"data.path={d / 'rec.csv'}", "data.control_columns=[u]", "data.observed=[q]", "data.segment=1.0"]
    given = {e.split("=", 1)[0] for e in extra}
    keys = [k for k in keys if k.split("=", 1)[0] not in given]
    return ["train", "model=equations", f"model.spec={d / 'rec.yaml'}", "trainer=whitebox", *keys, *extra]


def _cell(rows: list[str], row: int, column: int, value: str) -> list[str]:
    """`rows` (CSV lines) with the cell at 0-based `row`, `column` replaced by `value`."""
    cells = rows[row].split(",")
    cells[column] = value
    return [*rows[:row], ",".join(cells), *rows[row + 1 :]]


def _long_driven(d: Path) -> list[str]:
    """A long CSV whose column u is the driven spec's input, and a train run that does not list it as a control."""
    rows = [f"{b},{0.1 * k:.1f},0,{0.01 * k},{0.1 * b},{(k % 7) / 7}" for b in range(4) for k in range(11)]
    (d / "long.csv").write_text("traj,t,node,x,v,u\n" + "\n".join(rows) + "\n")
    (d / "driven.yaml").write_text(DRIVEN_SPEC)
    return [
        "train",
        "model=equations",
        f"model.spec={d / 'driven.yaml'}",
        f"data.path={d / 'long.csv'}",
        *TINY_TRAIN[:2],
    ]


DRIVEN_SPEC = (
    "states: [x, v]\ninputs: [u]\nequations: {x: v, v: -k*x + u}\nparams: {k: 4.0}\nnodes: 1\ndt: 0.1\nhorizon: 10\n"
)


def _driven(d: Path, command: str, *extra: str) -> list[str]:
    """A driven spec file in `d` and the `system=equations` command that simulates it."""
    (d / "driven.yaml").write_text(DRIVEN_SPEC)
    return [command, "system=equations", f"system.spec={d / 'driven.yaml'}", *extra]


def _declaring(ws: Path, d: Path, **sizes: int) -> Path:
    """The lorenz3 checkpoint with its model config declaring `sizes` its weights do not have."""
    return altered(ws, d, lambda p: p["model"]["config"].update(sizes))


@pytest.mark.parametrize("name", list(CASES))
def test_bad_input_ends_with_one_message(name, ws, tmp_path):
    if name.startswith("optuna_sweeper"):  # hydra/sweeper=optuna needs the `search` extra, as in test_sweeps.py
        pytest.importorskip("hydra_plugins.hydra_optuna_sweeper")
    case = CASES[name]
    args = case.args(ws, tmp_path)
    before = snapshot(tmp_path, ws)
    res = run_mpsim(args, tmp_path)
    assert res.code == case.code, (res.code, res.err[-2000:])
    assert "Traceback" not in res.err
    lines = res.error_lines() or [ln for ln in res.err.splitlines() if ln.startswith("mpsim")]
    assert len(lines) == 1 and case.match in lines[0], res.err[-2000:]
    for text in case.forbid:
        assert text not in res.err, res.err
    after = snapshot(tmp_path, ws)
    changed = [p for p in before if after.get(p) != before[p]]
    new = [p for p in after if p not in before and not any(a in str(p) for a in case.allow_new)]
    assert not changed, changed  # nothing lost, nothing rewritten
    assert not new, new  # nothing half-written, no half-made run directory
    assert not (tmp_path / "pwned.txt").exists() and not (tmp_path / "pwned2").exists()


def test_the_malicious_payload_is_live_without_the_allowlist(tmp_path):
    """The payload of `ckpt_malicious_effect` does write a file when instantiated: the refusal above is real."""
    from hydra.utils import instantiate

    instantiate(payload_effect(tmp_path / "pwned.txt"))
    assert (tmp_path / "pwned.txt").read_text() == "pwned"


# ---- outcomes when nothing is wrong, and faults in the middle of a run ------------------------------------------
def test_single_run_keeps_the_export_it_replaces(ws, tmp_path):
    args = _replace_export(ws, tmp_path)
    old = (tmp_path / "checkpoints" / "pendulum2.ckpt").read_bytes()
    res = run_mpsim(args, tmp_path)
    assert res.code == 0, res.err
    kept = [p for p in (tmp_path / "checkpoints").glob("pendulum2.*.ckpt")]
    assert len(kept) == 1 and kept[0].read_bytes() == old
    assert (tmp_path / "checkpoints" / "pendulum2.ckpt").read_bytes() != old
    assert "replaced an earlier export, kept as" in res.out and kept[0].name in res.out


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_sweep_jobs_keep_their_models_in_their_run_directories(ws, tmp_path):
    res = run_mpsim(["train", "-m", *TINY_TRAIN, "eval.plots=false", "seed=0,1"], tmp_path)
    assert res.code == 0, res.err
    assert not (tmp_path / "checkpoints").exists()
    bests = sorted((tmp_path / "outputs" / "multirun").rglob("best.ckpt"))
    assert len(bests) == 2 and res.out.count("a sweep job: its model stays in its run directory") == 2
    for best in bests:
        assert f"use init={best}" in res.out


def test_export_name_from_a_file_stays_inside_ckpt_dir(ws, tmp_path):
    meta = json.dumps({"system": "../../escaped", "state_names": ["theta", "omega"]})
    (tmp_path / "work").mkdir()
    path = write_npz(tmp_path / "work", meta=np.array(meta))
    res = run_mpsim(data_args(path), tmp_path / "work")
    assert res.code == 0, res.err
    assert not list(tmp_path.glob("escaped*")) and not list((tmp_path / "work").glob("escaped*"))
    assert [p.name for p in (tmp_path / "work" / "checkpoints").iterdir()] == ["escaped.ckpt"]


def test_divergence_in_epoch_1_does_not_claim_a_best_checkpoint(ws, tmp_path, monkeypatch):
    from mpsim.errors import DivergenceError
    from mpsim.training.trainer import Trainer

    def diverge(self, *args, **kwargs):
        raise DivergenceError("training diverged in epoch 1, batch 0: test")

    monkeypatch.setattr(Trainer, "_train_epoch", diverge)
    res = run_mpsim(["train", *TINY_TRAIN, "eval.plots=false"], tmp_path)
    assert res.code == 3
    assert "no epoch finished" in res.err and "best checkpoint so far" not in res.err
    assert not (tmp_path / "checkpoints").exists()  # nothing exported
    (summary,) = (tmp_path / "outputs").rglob("summary.json")
    assert json.loads(summary.read_text())["status"] == "diverged"


def test_failed_export_still_writes_the_summary(ws, tmp_path, monkeypatch):
    import mpsim.commands.train as train_cmd

    def full_disk(src, dst):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(train_cmd.shutil, "copyfileobj", full_disk)
    res = run_mpsim(["train", *TINY_TRAIN, "eval.plots=false"], tmp_path)
    assert res.code == 4 and "the disk is full" in res.err and "Traceback" not in res.err
    (summary,) = (tmp_path / "outputs").rglob("summary.json")
    saved = json.loads(summary.read_text())
    assert "disk is full" in saved["export_error"] and Path(saved["checkpoint"]).is_file()
    assert not [p for p in tmp_path.rglob("*.tmp")]  # no temporary file left behind


def test_full_disk_mid_command_leaves_nothing_half_written(ws, tmp_path, monkeypatch):
    import mpsim.files as files

    def full_disk(src, dst):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(files.os, "replace", full_disk)
    res = run_mpsim(["simulate", "n=2", "data.horizon=3"], tmp_path)
    assert res.code == 4 and "the disk is full" in res.err
    assert not [p for p in tmp_path.rglob("*") if p.is_file()]  # no data, no temp file, no run directory


@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o027, 0o640)])
def test_output_files_honour_the_umask(tmp_path, umask, mode):
    old = os.umask(umask)
    try:
        res = run_mpsim(["simulate", "n=2", "data.horizon=3", "format=both"], tmp_path)
    finally:
        os.umask(old)
    assert res.code == 0, res.err
    written = [p for p in (tmp_path / "outputs").rglob("*") if p.suffix in (".npz", ".csv", ".json")]
    assert len(written) >= 4
    assert {stat.S_IMODE(p.stat().st_mode) for p in written} == {mode}


def test_help_and_config_errors_do_not_import_torch(tmp_path):
    code = NO_TORCH + (
        "main(['--help'])\n"
        "assert 'torch' not in sys.modules, 'help imported torch'\n"
        "try:\n    main(['train', 'trainer.lrr=1'])\nexcept SystemExit as e:\n    assert e.code == 2\n"
        "assert 'torch' not in sys.modules, 'a config error imported torch'\n"
        "main(['train', '--cfg', 'job'])\n"
        "assert 'torch' not in sys.modules, '--cfg job imported torch'\n"
        "try:\n    main(['train', 'model=equations', 'model.spec=bomb.yaml'])\nexcept SystemExit as e:\n"
        "    assert e.code == 2\n"
        "assert 'torch' not in sys.modules, 'an alias-bomb spec imported torch before it was refused'\n"
    )
    (tmp_path / "bomb.yaml").write_text(billion_laughs())
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "Did you mean trainer.lr?" in proc.stderr and "usage: mpsim" in proc.stdout and "_target_" in proc.stdout
    assert "bomb.yaml: its anchors and aliases" in proc.stderr
    assert [p.name for p in tmp_path.iterdir()] == ["bomb.yaml"]  # no run directory for a config error


def test_a_billion_laughs_spec_is_refused_at_once(ws, tmp_path):
    """Issue 58: a 1.3 KB spec of nine levels of YAML aliases ran for minutes at 1.6 GB and left a run folder; it
    is refused while it is read, with one message, in far less than the (generous) 10 s allowed here."""
    args = _spec(tmp_path, billion_laughs())
    assert (tmp_path / "spec.yaml").stat().st_size < 1400

    def too_slow(signum, frame):
        raise RuntimeError("the alias bomb was still being read after 60 s")

    previous = signal.signal(signal.SIGALRM, too_slow)
    signal.alarm(60)  # the old code never returned: fail instead of hanging the suite
    start = time.perf_counter()
    try:
        res = run_mpsim(args, tmp_path)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    elapsed = time.perf_counter() - start
    assert res.code == 2, res.err[-2000:]
    (line,) = res.error_lines()
    assert "spec.yaml: its anchors and aliases (&name, *name) repeat more than 10,000 values" in line
    assert "Traceback" not in res.err
    assert elapsed < 10, elapsed
    assert [p.name for p in tmp_path.rglob("*") if p.is_file()] == ["spec.yaml"]  # no run folder left


def test_the_matrix_is_large_enough():
    assert len(CASES) >= 45


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_a_moved_run_resumes_where_it_is_now_and_writes_where_it_is_told(ws, tmp_path):
    """paths.* say where a run writes, not what it computes: a run directory copied to another place (another
    disk, another checkout) resumes there with new paths; anything else that differs is still refused."""
    moved = tmp_path / "elsewhere"
    run_dir = moved / "run"
    shutil.copytree(lorenz_run(ws), run_dir)
    ckpts = moved / "ckpts"
    # how it shows progress is not what it computes either: a run started with a bar resumes in the background
    shown = ["trainer.progress=false", "trainer.log_every_s=60", "trainer.log_every=5"]
    res = run_mpsim(
        ["train", f"resume={run_dir}", f"paths.ckpt_dir={ckpts}", f"paths.output_root={moved}", *shown], tmp_path
    )
    assert res.code == 0, res.err
    assert "mpsim train: lorenz3" in res.out
    assert (ckpts / "lorenz3.ckpt").is_file()  # exported where it was told, not where the run first wrote
    refused = run_mpsim(["train", f"resume={run_dir}", f"paths.ckpt_dir={ckpts}", *shown, "trainer.lr=0.5"], tmp_path)
    assert refused.code == 2, refused.err
    (line,) = refused.error_lines()
    assert "trainer.lr=0.5 (not set in the run)" in line
    assert not any(key in line.split(". A resumed")[0] for key in ("paths.ckpt_dir=", "trainer.progress", "log_every"))


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_a_run_moved_from_a_gpu_machine_resumes_on_the_cpu_when_told_to(ws, tmp_path):
    """The hardware a run computes on (device, threads) is not what it computes: a run whose record says
    device=cuda (started on a GPU machine, its folder copied here, where there is no CUDA) is refused with the
    fix named, then resumes with device=cpu and says so; what it computes still may not change."""
    run_dir = tmp_path / "from_gpu"
    shutil.copytree(lorenz_run(ws), run_dir)
    record = run_dir / ".hydra" / "overrides.yaml"
    record.write_text(record.read_text() + "- device=cuda\n- threads=4\n")  # as the GPU machine recorded it
    if not torch.cuda.is_available():
        as_recorded = run_mpsim(["train", f"resume={run_dir}"], tmp_path)
        assert as_recorded.code == 2, as_recorded.err
        (line,) = as_recorded.error_lines()
        assert "device=cuda" in line and "use device=cpu" in line
    res = run_mpsim(["train", f"resume={run_dir}", "device=cpu", "threads=1"], tmp_path)
    refused = run_mpsim(["train", f"resume={run_dir}", "device=cpu", "dtype=float64"], tmp_path)
    assert refused.code == 2, refused.err
    assert "dtype=float64 (not set in the run)" in refused.err and "device=cpu (" not in refused.err
    assert res.code == 0, res.err
    assert "resuming with device=cpu (the run has device=cuda)" in res.err
    assert "resuming with threads=1 (the run has threads=4)" in res.err
    assert "resuming after epoch" in res.err  # it went on from last.ckpt
    assert record.read_text().endswith("- device=cuda\n- threads=4\n")  # the record keeps what it was


@pytest.mark.slow  # long; outside the default suite (<4 min on 2 cores), run by .ci/run's -m slow step
def test_a_run_on_a_data_file_resumes_with_the_file_moved_along_only_if_it_holds_the_same_bytes(ws, tmp_path):
    """A results folder copied elsewhere carries its data file: `data.path` may then point at the copy, checked
    against the SHA-256 the run recorded (data.json); other bytes are refused, and so is a file that cannot be
    checked (no record, the original gone)."""
    first = tmp_path / "first"
    run_mpsim_ok(["simulate", "system=lorenz3", "n=12", "data.seed=3", f"hydra.run.dir={first}/sim"], tmp_path)
    data = first / "data.npz"
    shutil.move(first / "sim" / "trajectories.npz", data)
    run_dir = first / "run"
    run_mpsim_ok(["train", f"data.path={data}", *TINY_TRAIN, f"hydra.run.dir={run_dir}"], tmp_path)
    record = json.loads((run_dir / "data.json").read_text())
    assert record["path"] == str(data) and len(record["sha256"]) == 64
    moved = tmp_path / "moved"
    shutil.copytree(first, moved)
    shutil.rmtree(first)  # the original data file is gone: only the recorded digest can vouch for the copy
    resume = ["train", f"resume={moved / 'run'}", f"paths.output_root={moved}"]
    res = run_mpsim([*resume, f"data.path={moved / 'data.npz'}"], tmp_path)
    assert res.code == 0, res.err
    run_mpsim_ok(["simulate", "system=lorenz3", "n=12", "data.seed=4", f"hydra.run.dir={tmp_path}/other"], tmp_path)
    refused = run_mpsim([*resume, f"data.path={tmp_path / 'other' / 'trajectories.npz'}"], tmp_path)
    assert refused.code == 2
    assert "only if it holds the same bytes" in refused.err
    deep = "[" * 100_000 + "]" * 100_000  # used to end in a RecursionError traceback
    for bad in ("{not json", '{"sha256": "../../etc/passwd", "path": "/etc/passwd"}', "[1, 2]", "", deep):
        (moved / "run" / "data.json").write_text(bad)  # a damaged or forged record vouches for nothing
        unchecked = run_mpsim([*resume, f"data.path={moved / 'data.npz'}"], tmp_path)
        assert unchecked.code == 2, bad
        assert "recorded no digest" in unchecked.err
    (moved / "run" / "data.json").unlink()
    unchecked = run_mpsim([*resume, f"data.path={moved / 'data.npz'}"], tmp_path)
    assert unchecked.code == 2
    assert "recorded no digest" in unchecked.err


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_resume_uses_the_runs_own_overrides_and_keeps_its_record(ws, tmp_path):
    run_dir = tmp_path / "run"
    shutil.copytree(lorenz_run(ws), run_dir)
    record = {p.name: p.read_bytes() for p in (run_dir / ".hydra").iterdir()}
    res = run_mpsim(["train", f"resume={run_dir}"], tmp_path)
    assert res.code == 0, res.err
    assert "mpsim train: lorenz3" in res.out  # the run's own system=lorenz3, not the default pendulum2
    assert {p.name: p.read_bytes() for p in (run_dir / ".hydra").iterdir()} == record


# ---- model sizes and data metadata from files ------------------------------------------------------------------
@pytest.fixture
def allocations(monkeypatch):
    """The element counts of every parameter created with storage (not on the meta device) while a test runs."""
    sizes: list[int] = []
    real_new = torch.nn.Parameter.__new__

    def spy(cls, data=None, requires_grad=True):
        if data is not None and data.device.type != "meta":
            sizes.append(data.numel())
        return real_new(cls, data, requires_grad)

    monkeypatch.setattr(torch.nn.Parameter, "__new__", staticmethod(spy))
    return sizes


@pytest.mark.parametrize("command", ["eval", "train"])
def test_sizes_a_checkpoint_declares_are_refused_before_they_are_allocated(command, ws, tmp_path, allocations):
    """An 11 kB checkpoint declaring hidden=12000 used to cost ~600 MB before its weights were found not to fit:
    no parameter of the declared size [3000, 3000] may now be created at all."""
    bad = _declaring(ws, tmp_path, hidden=3000)
    extra = TINY_TRAIN if command == "train" else []
    res = run_mpsim([command, f"init={bad}", "system=lorenz3", *EVAL, *extra], tmp_path)
    assert max(allocations, default=0) <= 32 * 32, max(allocations)  # the checkpoint's own largest weight
    assert res.code == 2 and "its model.config does not describe its weights" in res.err, res.err[-2000:]


def test_large_data_metadata_is_not_copied_into_the_checkpoints_or_the_summary(tmp_path):
    """A data file's `meta` of megabytes used to be copied into best.ckpt, last.ckpt (every epoch), the export and
    summary.json; checkpoints keep what mpsim reads back, and the rest up to 64 kB."""
    meta = {"system": "measured", "state_names": ["theta", "omega"], "notes": "x" * 2_000_000}
    meta["params"] = {"k": 1.0, "calibration": [0.5] * 200_000}
    path = write_npz(tmp_path, meta=np.array(json.dumps(meta)))
    res = run_mpsim([*data_args(path), "trainer.max_epochs=2"], tmp_path)
    assert res.code == 0, res.err[-2000:]
    (run,) = (tmp_path / "outputs" / "train").glob("*/*")
    files = [
        run / "checkpoints" / "best.ckpt",
        run / "checkpoints" / "last.ckpt",
        tmp_path / "checkpoints" / "measured.ckpt",
    ]
    sizes = {p.name: p.stat().st_size for p in [*files, run / "summary.json"]}
    assert max(sizes.values()) < 100_000, sizes
    kept = torch.load(files[0], weights_only=True)["system"]
    assert kept["system"] == "measured" and kept["state_names"] == ["theta", "omega"] and "notes" not in kept
    assert json.loads((run / "summary.json").read_text())["system"]["params"] == {"k": 1.0}
    assert "data metadata not copied into the checkpoints" in res.err and "notes (2 MB)" in res.err


# ---- run folders (issue 58) -------------------------------------------------------------------------------------
def test_overwrite_true_moves_the_earlier_run_to_a_backup_first(ws, tmp_path):
    """Training into a finished run's folder with overwrite=true: the earlier run, every file of it, is in
    `backup-<time>/` unchanged; the new run is in the folder."""
    args = _into_a_run(ws, tmp_path, ["train", "system=lorenz3", *TINY_TRAIN, "eval.plots=false", "export=false"])
    run = tmp_path / "run"
    before = {p.relative_to(run): p.read_bytes() for p in run.rglob("*") if p.is_file()}
    res = run_mpsim([*args, "overwrite=true"], tmp_path)
    assert res.code == 0, res.err[-2000:]
    (backup,) = run.glob("backup-*")
    assert {p.relative_to(backup): p.read_bytes() for p in backup.rglob("*") if p.is_file()} == before
    assert f"moved the {len(list(backup.iterdir()))} earlier entries of {run} to {backup}" in res.err
    assert (run / "checkpoints" / "best.ckpt").is_file() and (run / ".hydra" / "overrides.yaml").is_file()
    assert "overwrite=true" in (run / ".hydra" / "overrides.yaml").read_text()


def test_overwrite_true_then_a_bad_input_puts_the_earlier_run_back(ws, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(lorenz_run(ws), run)
    before = snapshot(run)
    x = np.random.default_rng(0).normal(size=(6, 6, 2, 2))
    x[1, 2, 0, 1] = np.inf
    res = run_mpsim([*data_args(write_npz(tmp_path, x=x)), f"hydra.run.dir={run}", "overwrite=true"], tmp_path)
    assert res.code == 2 and "`x` has NaN/inf" in res.err, res.err[-2000:]
    assert snapshot(run) == before and not list(run.glob("backup-*"))


def test_the_hint_after_ctrl_c_resumes_a_run_in_a_folder_of_its_own(tmp_path, monkeypatch):
    """`resume=true` finds runs in the default folders only: a run started with hydra.run.dir= is told to resume
    with its folder named, and that command does continue it."""
    from mpsim.training.trainer import Trainer

    train_epoch = Trainer._train_epoch

    def ctrl_c_in_epoch_2(self, model, data, opt, loss_fn, shuffle, epoch):
        if epoch == 2:
            raise KeyboardInterrupt
        return train_epoch(self, model, data, opt, loss_fn, shuffle, epoch)

    monkeypatch.setattr(Trainer, "_train_epoch", ctrl_c_in_epoch_2)
    cut = run_mpsim(["train", *TINY_TRAIN, "eval.plots=false", "hydra.run.dir=mine/run"], tmp_path)
    monkeypatch.undo()
    assert cut.code == 130 and "interrupted" in cut.err, cut.err[-2000:]
    (hint,) = [ln.strip() for ln in cut.err.splitlines() if ln.strip().startswith("mpsim train ")]
    res = run_mpsim(shlex.split(hint)[1:], tmp_path)
    assert res.code == 0, (hint, res.err[-2000:])
    assert "resuming after epoch 1" in res.err
    assert len(pd.read_csv(tmp_path / "mine" / "run" / "metrics.csv")) == 4  # epochs 0..3, as one run writes


def test_ctrl_c_before_anything_is_saved_leaves_the_folder_as_it_was(tmp_path, monkeypatch):
    import mpsim.commands.train as train_cmd

    def ctrl_c(*args, **kwargs):
        raise KeyboardInterrupt

    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine\n")
    before = snapshot(tmp_path)
    monkeypatch.setattr(train_cmd, "prepare", ctrl_c)
    res = run_mpsim(["train", *TINY_TRAIN, "hydra.run.dir=mine/new/run"], tmp_path)
    assert res.code == 130 and "Nothing was saved yet" in res.err and "resume=" not in res.err, res.err
    assert snapshot(tmp_path) == before and not (tmp_path / "mine" / "new").exists()


def test_orphaned_temporary_files_are_removed_and_live_ones_kept(ws, tmp_path):
    """kill -9 during an export leaves `.<name>.mpsim-<pid>-<host>.<random>.tmp`; the next write into that folder
    removes it once its process is gone and it is old, and never a live process's file or another host's."""
    host = hashlib.sha256(socket.gethostname().encode()).hexdigest()[:8]
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    ckpts = tmp_path / "checkpoints"
    ckpts.mkdir()
    old = time.time() - 3600

    def temp(name: str, pid: int, where: str = host, age: float = old) -> Path:
        path = ckpts / f".{name}.mpsim-{pid}-{where}.k2j_x9ab.tmp"
        path.write_bytes(b"half a checkpoint")
        os.utime(path, (age, age))
        return path

    orphan = temp("pendulum2.ckpt", gone.pid)
    kept = [
        temp("a.ckpt", os.getpid()),  # a live process (a parallel sweep job) still writes it
        temp("b.ckpt", gone.pid, age=time.time()),  # too recent to call orphaned
        temp("c.ckpt", gone.pid, where="0123abcd"),  # another host's process: cannot be checked from here
    ]
    res = run_mpsim(["train", *TINY_TRAIN, "eval.plots=false"], tmp_path)
    assert res.code == 0, res.err[-2000:]
    assert not orphan.exists() and all(p.exists() for p in kept)
    assert (ckpts / "pendulum2.ckpt").is_file()
