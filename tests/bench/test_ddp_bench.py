"""`mpsim bench bench=ddp`: 1 and 2 processes run the same training steps (same loss), and the rows it reports."""

from __future__ import annotations

import pytest
import torch

from mpsim.bench.ddp import DDPBench
from mpsim.errors import ConfigError


def test_refuses_unknown_cases_and_a_missing_gpu():
    with pytest.raises(ConfigError, match="choose from nbody, mpnode"):
        DDPBench(cases=["lorenz"])
    for processes in ([], [0]):  # [] was "min() arg is an empty sequence"
        with pytest.raises(ConfigError, match=r"need bench.processes \(a non-empty list\)"):
            DDPBench(processes=processes)
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="CUDA is not available"):
            DDPBench(device="cuda")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_one_gpu_process_runs_the_step():
    (row,) = DDPBench(cases=["mpnode"], processes=[1], mpnode_batch=4, mpnode_steps=5, steps=1, device="cuda").run()
    assert row["device"] == "cuda" and row["step_s"] > 0


@pytest.mark.slow
def test_two_processes_do_the_work_of_one():
    bench = DDPBench(cases=["mpnode"], processes=[1, 2], mpnode_batch=6, mpnode_steps=5, steps=2, repeats=2, warmup=1)
    one, two = bench.run()
    assert (one["processes"], one["backend"], two["processes"], two["backend"]) == (1, "none", 2, "gloo")
    assert two["final_loss"] == pytest.approx(one["final_loss"], rel=1e-4)  # float32, summation order only
    assert one["speedup"] == 1.0 and two["speedup"] > 0 and two["samples_per_s"] == pytest.approx(6 / two["step_s"])
    assert bench.summarise([one, two])[0].startswith("- mpnode: 2 processes run")
