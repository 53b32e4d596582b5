"""cli/keep_runs.sh, which copies a recipe's runs into results/: small files only, and a finished run's
last.ckpt (never resumed) left out unless a note or bench names it."""

import os
import subprocess
from pathlib import Path

KEEP = Path(__file__).resolve().parents[1] / "cli" / "keep_runs.sh"


def runs(root: Path) -> Path:
    """A recipe's output: a finished run, an interrupted one, a finished one a bench starts from, big data."""
    src = root / "out"
    for run, finished in (("col/done", True), ("col/cut", False), ("col/named", True)):
        ckpts = src / run / "checkpoints"
        ckpts.mkdir(parents=True)
        (ckpts / "last.ckpt").write_bytes(b"L" * 1500)
        (ckpts / "best.ckpt").write_bytes(b"B" * 500)
        (src / run / "metrics.csv").write_text("epoch,loss\n0,1.0\n")
        if finished:
            (src / run / "summary.json").write_text("{}")
    (src / "col" / "data.npz").write_bytes(b"D" * 3 * 1024)  # over MAX_KB=2
    bench = root / "results" / "bench_x"
    bench.mkdir(parents=True)
    (bench / "COMMAND.md").write_text("mpsim bench ... init=results/kept/col/named/checkpoints/last.ckpt\n")
    return src


def keep(root: Path, src: Path, **env: str) -> subprocess.CompletedProcess:
    environ = {**os.environ, "RESULTS": str(root / "results"), "MAX_KB": "2", **env}
    return subprocess.run(["bash", str(KEEP), str(src), "kept"], env=environ, capture_output=True, text=True)


def kept_files(root: Path) -> set[str]:
    dest = root / "results" / "kept"
    return {str(p.relative_to(dest)) for p in dest.rglob("*") if p.is_file()}


def test_a_finished_runs_last_checkpoint_is_left_out_unless_something_names_it(tmp_path):
    res = keep(tmp_path, runs(tmp_path))
    assert res.returncode == 0, res.stderr
    files = kept_files(tmp_path)
    assert "col/done/checkpoints/last.ckpt" not in files  # finished, named by nothing: left out
    assert "left out (finished run, not resumed): col/done/checkpoints/last.ckpt" in res.stdout
    assert {"col/done/checkpoints/best.ckpt", "col/done/summary.json", "col/done/metrics.csv"} <= files
    assert "col/cut/checkpoints/last.ckpt" in files  # interrupted: it resumes from it
    assert "col/named/checkpoints/last.ckpt" in files  # a bench starts from it
    assert "col/data.npz" not in files and "left out (over 2 KB): ./col/data.npz" in res.stdout
    assert not list((tmp_path / "results").glob(".keep.*"))  # no staging folder left behind


def test_finished_last_keeps_every_checkpoint(tmp_path):
    res = keep(tmp_path, runs(tmp_path), FINISHED_LAST="1")
    assert res.returncode == 0, res.stderr
    assert {f"col/{r}/checkpoints/last.ckpt" for r in ("done", "cut", "named")} <= kept_files(tmp_path)
    assert "not resumed" not in res.stdout
