"""Values the model's precision can hold: data read from a file is refused, with the file named, when it would
overflow float32 (or float64 once squared) or when its time points merge in float32."""

from __future__ import annotations

import numpy as np
import torch

from mpsim.data.trajectories import Trajectories
from mpsim.errors import DataError


def check_representable(data: Trajectories, dtype_name: str, source: str) -> None:
    """Refuse values that overflow the model's precision (reported as overflow, not as NaN/inf later).

    float32 holds magnitudes up to 3.4e38; normalisation squares values, so float64 data must stay below 1e150.
    Time points are checked too (`_check_times`).
    """
    _check_times(data.t, dtype_name, source)
    limit, why = (
        (float(np.finfo(np.float32).max), "overflow float32 (largest 3.4e38)")
        if dtype_name == "float32"
        else (1e150, "overflow float64 when squared for the normalisation statistics")
    )
    for name, tensor in (("x", data.x), ("u", data.u)):
        if tensor is None:
            continue
        peak = float(tensor.abs().max())
        if peak > limit:
            index = tuple(int(i) for i in torch.nonzero(tensor.abs() == peak)[0])
            fix = (
                "rescale the data (other units) or use dtype=float64" if dtype_name == "float32" else "rescale the data"
            )
            raise DataError(f"{source}: {name}{list(index)} = {peak:.3g}: values this large {why}. Fix: {fix}.")


def _check_times(t: torch.Tensor, dtype_name: str, source: str) -> None:  # t: [T] time points, float64
    """Time points the model's precision holds: within float32's range and still strictly increasing once rounded
    to float32 (dtype=float32), with steps that do not overflow float64. Each refusal names the range of `t`."""
    low, high = float(t.min()), float(t.max())
    shown = f"`t` runs from {low} to {high}"  # every digit: neighbours that float32 merges differ late
    fix = "subtract the start time or measure time in a larger unit"
    if dtype_name == "float32" and max(abs(low), abs(high)) > float(np.finfo(np.float32).max):
        raise DataError(
            f"{source}: {shown}: values this large overflow float32 (largest 3.4e38), the precision of "
            f"dtype=float32. Fix: {fix}, or use dtype=float64."
        )
    if not torch.isfinite(t[1:] - t[:-1]).all():
        raise DataError(f"{source}: {shown}: the steps between time points overflow float64. Fix: {fix}.")
    if dtype_name == "float32":
        rounded = t.float()
        tied = torch.nonzero(rounded[1:] <= rounded[:-1])
        if len(tied):
            k = int(tied[0])
            raise DataError(
                f"{source}: {shown}: t[{k}] = {float(t[k])} and t[{k + 1}] = {float(t[k + 1])} are the "
                f"same number in float32 (about 7 significant digits, dtype=float32). Fix: {fix}, or use "
                "dtype=float64."
            )
