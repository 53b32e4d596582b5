"""Model-based estimates of states that are not measured: Kalman smoothers over a nominal model's step and output.

Pure functions on tensors (no configs, no data containers): `kalman_smoother` (extended or unscented, optionally
iterated) and `choose_process_noise` (the scale of Q by the measurements' likelihood). See docs/estimation.md.
"""

from mpsim.estimate.kalman import Smoothed as Smoothed
from mpsim.estimate.kalman import kalman_smoother as kalman_smoother
from mpsim.estimate.noise import ProcessNoiseChoice as ProcessNoiseChoice
from mpsim.estimate.noise import choose_process_noise as choose_process_noise

__all__ = ["Smoothed", "kalman_smoother", "ProcessNoiseChoice", "choose_process_noise"]
