"""Figure 7: each quadrotor run's lowest test error so far at matched epochs, and m = 20 against m = 7 and 13,
from the runs' metrics.csv alone: `python results/message_size_paper/compare_quad.py [EPOCH ...]`."""
import math
import sys
from pathlib import Path

import pandas as pd

from mpsim.report import min_so_far  # the message-size report's own "lowest so far"

R = Path(__file__).parent  # results/message_size_paper
runs = {n: R / p / "metrics.csv" for n, p in [
    ("q3 m7", "quad/quad3_m7_s0"), ("q3 m13", "quad/quad3_m13_s0"), ("q3 m20", "quad/quad3_m20_s0"),
    ("q3 L2S", "quad_l2s/quad3_s0"), ("q6 m7", "quad/quad6_m7_s0"), ("q6 m13", "quad/quad6_m13_s0"),
    ("q6 m20", "quad/quad6_m20_s0"), ("q6 L2S", "quad_l2s/quad6_s0")]}
marks = [int(x) for x in (sys.argv[1:] or [500, 1000, 1500, 2000, 2500, 3000, 3500, 4000])]
best = {}
for name, path in runs.items():
    curve = pd.read_csv(path)
    trained = curve[curve["epoch"] >= 1]
    at = trained.loc[trained["test_error"].idxmin()]
    low, argmin = float(at["test_error"]), int(at["epoch"])
    by = {m: v for m, v in zip(marks, min_so_far(curve, marks)) if not math.isnan(v)}
    best[name] = by
    last = trained.iloc[-1]
    print(f"{name:7s} epochs {int(last['epoch']):>5d} min {low:.4f} @ {argmin} exm {low*argmin:.1f} wall {float(last['wall_time'])/3600:.2f} h  "
          + " ".join(f"{m}:{by[m]:.4f}" for m in marks if m in by))
for q in ("q3", "q6"):
    for other in ("m7", "m13"):
        a, b = best[f"{q} m20"], best[f"{q} {other}"]
        print(f"{q} m20 vs {other}: " + " ".join(f"{m}:{100*(a[m]/b[m]-1):+.1f}%" for m in marks if m in a and m in b))
