"""`mpsim train` on a measured recording as it comes: a wide CSV holding positions and a measured input, from an
integrator that is not mpsim's (fixed-step RK4 at a twentieth of the sample step, input held between samples)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.helpers import run_mpsim, run_mpsim_ok

M, C, K = 1.0, 0.4, 4.0  # mass, viscous damping, stiffness of the truth


def _record(path: Path, seconds: float = 12.0, dt: float = 0.01, seed: int = 0) -> None:
    """A driven damped oscillator, q' = v, v' = (u − C v − K q)/M, u a random-phase multisine held per sample;
    the file holds time, position and input only (no velocity)."""
    rng = np.random.default_rng(seed)
    n = int(round(seconds / dt))
    t = dt * np.arange(n + 1)
    freqs = np.array([0.2, 0.45, 0.8, 1.3])
    phases = rng.uniform(0, 2 * np.pi, freqs.size)
    u = np.sin(2 * np.pi * freqs[None, :] * t[:, None] + phases).sum(1)

    def f(y: np.ndarray, uk: float) -> np.ndarray:
        return np.array([y[1], (uk - C * y[1] - K * y[0]) / M])

    y, h, q = np.array([0.3, 0.0]), dt / 20, [0.3]
    for k in range(n):  # a loop over time steps of the test's own reference integrator
        for _ in range(20):
            k1 = f(y, u[k])
            k2 = f(y + h / 2 * k1, u[k])
            k3 = f(y + h / 2 * k2, u[k])
            k4 = f(y + h * k3, u[k])
            y = y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        q.append(y[0])
    rows = "\n".join(f"{a:.6f}, {b:.9f}, {c:.9f}" for a, b, c in zip(t, q, u, strict=True))
    path.write_text('"time", "enc", "drive",\n' + rows.replace("\n", ",\n") + ",\n")  # quoted, trailing delimiter


SPEC = """states: [q, v]
inputs: [u]
equations:
  q: v
  v: (u - c*v - k*q)/m
params: {m: 1.0, c: 0.3, k: 3.5}
learnable: [c, k]
"""


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_train_on_a_wide_csv_with_positions_only(tmp_path):
    _record(tmp_path / "rec.csv")
    (tmp_path / "osc.yaml").write_text(SPEC)
    keys = [
        "model=equations",
        "model.spec=osc.yaml",
        "trainer=whitebox",
        "trainer.max_epochs=8",
        "data.path=rec.csv",
        "data.time_column=time",
        "data.columns={q: enc, u: drive}",
        "data.control_columns=[u]",
        "data.observed=[q]",
        "data.input_hold=zoh",
        "data.segment=2.0",
        "eval.plots=false",
        "hydra.run.dir=run",
    ]
    run_mpsim_ok(["train", *keys], tmp_path)
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    fitted = summary["model"]["physical_parameters"]
    assert abs(fitted["k"] - K) / K < 0.02 and abs(fitted["c"] - C) / C < 0.05, fitted  # from 3.5 and 0.3


def test_recording_keys_on_a_batch_file_are_one_message(tmp_path):
    (tmp_path / "long.csv").write_text("traj,t,node,x\n0,0,0,1\n0,1,0,2\n0,2,0,3\n1,0,0,1\n1,1,0,2\n1,2,0,3\n")
    res = run_mpsim(["train", "data.path=long.csv", "data.segment=1.0", "hydra.run.dir=run"], tmp_path)
    assert res.code == 2 and "data.segment apply to recordings" in res.err
    assert not (tmp_path / "run").exists()


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_a_pattern_run_says_what_it_read_and_keeps_it(tmp_path):
    """Console, summary.json and the checkpoint say which files and seconds were read, skipped, split and scored;
    the run is named after the pattern; a model fitted to zoh inputs warns when run on linear ones."""
    (tmp_path / "recs").mkdir()
    _record(tmp_path / "recs" / "long.csv", seconds=6.0)
    _record(tmp_path / "recs" / "short.csv", seconds=0.5, seed=1)  # shorter than a segment
    (tmp_path / "osc.yaml").write_text(SPEC)
    keys = [
        "model=equations",
        "model.spec=osc.yaml",
        "data.path=recs/*.csv",
        "data.time_column=time",
        "data.columns={q: enc, u: drive}",
        "data.observed=[q]",
        "data.segment=1.0",
        "eval.plots=false",
    ]
    res = run_mpsim_ok(["train", *keys, "trainer=whitebox", "trainer.max_epochs=1", "data.input_hold=zoh"], tmp_path)
    said = res.out + res.err
    assert "matched 2 files: long.csv, short.csv" in said
    assert "short.csv: 51 rows, 0–0.5 s; not used: its 51 samples are shorter than one segment (1 s)" in said
    assert "data: train: long.csv 0–4 s; val: long.csv 4–5 s; test: long.csv 5–6 s" in said
    assert "inputs ['u'] read from the files' columns" in said  # the spec's inputs; data.control_columns not given
    (run,) = (tmp_path / "outputs" / "train").glob("*/*_recs")  # named after the pattern's folder
    data = json.loads((run / "summary.json").read_text())["data"]
    assert data["covers"]["test"] == "long.csv 5–6 s" and len(data["accounts"][0]["files"]) == 2
    ckpt = tmp_path / "checkpoints" / "recordings.ckpt"
    res = run_mpsim_ok(["eval", f"init={ckpt}", *keys[2:], "data.split=[0,0,1]"], tmp_path)
    assert "fitted to inputs held 'zoh' between samples, but these data hold them 'linear'" in res.out + res.err


@pytest.mark.slow  # 4–13 s on 2 cores: the default suite stays under 4 minutes (.ci/run runs it)
def test_a_benchmark_split_is_scored_by_free_run_of_each_test_record(tmp_path):
    """data.train_range / data.test_range as a benchmark states them; every test record simulated whole from its
    first samples, scored in the signal's units, drawn; the summary says which samples were scored."""
    for k in (1, 2):
        _record(tmp_path / f"rec_{k}.csv", seconds=6.0, seed=k)
    (tmp_path / "osc.yaml").write_text(SPEC)
    keys = [
        "model=equations",
        "model.spec=osc.yaml",
        "trainer=whitebox",
        "data.path=rec_*.csv",
        "data.time_column=time",
        "data.columns={q: enc, u: drive}",
        "data.observed=[q]",
        "data.input_hold=zoh",
        "data.train_range=[0,400]",
        "data.test_range=[400,601]",
        "data.segment=1.0",
        "eval.init_samples=4",
        "hydra.run.dir=run",
    ]
    res = run_mpsim_ok(["train", *keys], tmp_path)
    said = res.out + res.err
    assert "test: rec_1.csv rows 400–600 (4–6 s), rec_2.csv rows 400–600 (4–6 s)" in said
    assert "each test record from its first 4 samples (eval.init_samples) to its end, open loop" in said
    free = json.loads((tmp_path / "run" / "summary.json").read_text())["freerun"]
    assert free["init_samples"] == 4 and [r["length"] for r in free["records"]] == [201, 201]
    for rec in free["records"]:
        q = rec["channels"]["q"]
        assert q["samples"] == 197 and q["fit"] > 95 and q["rmse"] < 0.01, q  # the fitted model, run open loop
    assert sorted(p.name for p in (tmp_path / "run" / "plots").glob("free_run_*.png")) == [
        "free_run_0_rec_1.png",
        "free_run_1_rec_2.png",
    ]
