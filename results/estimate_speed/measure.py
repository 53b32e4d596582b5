"""Wall time of `mpsim.estimate.kalman_smoother` with a cheap step (a linear 3-state step with an input, one output),
float64, one torch thread: B = 64 records × T = 200, one record of T = 100 000, and that record cut into 500
segments of 200 samples passed as records. Run from the repository root:

    PYTHONPATH=src python results/estimate_speed/measure.py [repeats]
"""

import sys
import time

import torch

from mpsim.estimate import kalman_smoother

D = 3
A = torch.tensor([[1.0, 0.01, 0.0], [-0.01, 0.99, 0.01], [0.0, 0.0, 0.98]], dtype=torch.float64)
GAIN = torch.tensor([0.0, 0.0, 0.01], dtype=torch.float64)


def seconds(B: int, T: int, method: str) -> float:
    g = torch.Generator().manual_seed(0)
    u = torch.randn(B, T, generator=g, dtype=torch.float64)  # [B, T] each record's input
    y = torch.randn(B, T, 1, generator=g, dtype=torch.float64)  # [B, T, 1]

    def step(x: torch.Tensor, k: int) -> torch.Tensor:  # x [B, R, D]
        return x @ A.mT + u[:, k, None, None] * GAIN

    def output(x: torch.Tensor, k: int) -> torch.Tensor:  # x [B, R, D] -> [B, R, 1]
        return x[..., :1]

    eye = torch.eye(D, dtype=torch.float64)
    start = time.perf_counter()
    kalman_smoother(
        step, output, y, torch.zeros(B, D, dtype=torch.float64), eye, 1e-4 * eye, 0.1 * torch.eye(1), method
    )
    return time.perf_counter() - start


def main(repeats: int = 3) -> None:
    torch.set_num_threads(1)
    seconds(2, 10, "ekf")
    seconds(2, 10, "ukf")
    print("| method | B × T | wall s (best of runs) | ms per sample step |")
    print("|---|---|---|---|")
    for method in ("ekf", "ukf"):
        for B, T, runs in ((64, 200, repeats), (1, 100_000, 1), (500, 200, repeats)):
            best = min(seconds(B, T, method) for _ in range(runs))
            print(f"| {method} | {B} × {T} | {best:.2f} | {1000 * best / T:.2f} |")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 3)
