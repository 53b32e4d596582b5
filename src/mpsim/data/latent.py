"""Unmeasured states (`data.observed`): a first estimate of each latent state from the states the file holds.

A latent state s whose equation is ``o' = s`` for a measured o (a velocity, when only positions are measured) is
estimated as the Savitzky–Golay derivative of o (`scipy.signal.savgol_filter`, polynomial order 2). These are the
starting values that a fit refines; the report says which states were estimated and how (``meta['estimated']``).

Window rule (`savgol_window`): the window spans the time o takes to move 10 of its resolution steps, and at least
5 samples. o's resolution δ is the larger of its quantisation step and √12 times its noise level (the spread of a
uniform rounding error of one step is step/√12; `mpsim.data.noise`). A local fit over W samples that span 10δ
leaves a derivative noise of about 1/(10√W) of the typical speed (under 5 % at W = 5), while the window stays as
short as the signal's motion allows, which keeps the curvature bias small. "The time to move 10δ" is the shortest
lag j at which the mean |o(t + j·dt) − o(t)| reaches 10δ (searched by doubling, then bisection).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np
import torch

from mpsim.data.noise import grid_quantum, noise_level
from mpsim.data.trajectories import Trajectories, grid_step
from mpsim.errors import DataError

POLYORDER = 2
MIN_WINDOW = 5
#: resolution steps that o moves within one window
STEPS_PER_WINDOW = 10
#: the least gain of the Savitzky–Golay derivative at the signal's dominant frequency for it to be the estimate
#: (5 samples at 8.6 samples a period: 0.73; a model-based estimate takes over below this)
MIN_GAIN = 0.9


def estimate_latent(
    data: Trajectories,
    derivative_of: Mapping[str, str],
    window_s: float | None = None,
    states: Sequence[str] | None = None,
    pending: Sequence[str] = (),
    model_based: bool = False,
) -> Trajectories:
    """`data` with every latent state filled by the smoothed derivative of the measured state it is the rate of.

    Args:
        data: [B, T, N, D_obs] the measured states (`data.observed`) on a uniform grid.
        derivative_of: {latent state s: measured o} for each equation ``o' = s`` of the model.
        window_s: the Savitzky–Golay window in seconds (None: `savgol_window`'s rule, per measured state).
        states: the model's states in its order (default: the measured ones, then the latent ones in the order of
            `derivative_of`); each must be measured, a key of `derivative_of` or `pending`.
        pending: latent states that no measured state is the rate of (an upper tank's level, a drive's current):
            filled with zeros here and listed in ``meta['pending']``, for the model-based estimate that needs the
            model (`mpsim.models.latent`).
        model_based: a model can estimate latent states (a spec): a rate state whose Savitzky–Golay derivative
            flattens the signal's dominant frequency (gain under `MIN_GAIN`) is left to it too (``meta['pending']``).

    Returns:
        [B, T, N, len(states)] states, with ``meta['observed']`` (the measured names), ``meta['estimated']``
        ({s: "Savitzky–Golay derivative of o, window W samples (… s), polyorder 2"}) and ``meta['derived_from']``
        ({s: o}: how the residual loop's null data estimate s again, `mpsim.data.measurement`).

    Raises:
        DataError: a latent state with no measured state to differentiate, or a grid that is not uniform.
    """
    observed = data.state_names
    latent = [s for s in derivative_of if s not in observed]
    order = list(states) if states is not None else observed + latent + list(pending)
    _check_names(data, {**derivative_of, **{s: "" for s in pending}}, [*observed, *pending], order)
    dt = grid_step(data.t)
    if latent and not np.isfinite(dt):
        raise DataError(
            f"{data.meta.get('source', 'data')}: estimating {latent} needs a uniform time grid; interpolate onto one "
            "with data.resample=<dt>."
        )
    x = data.x.double()
    filled: dict[str, torch.Tensor] = {name: x[..., k] for k, name in enumerate(observed)}
    filled.update({name: torch.zeros_like(x[..., 0]) for name in pending})
    estimated: dict[str, str] = {}
    narrow: dict[str, str] = {}  # latent states whose derivative's bandwidth does not fit: the model estimates them
    for s in latent:  # a loop over the few latent states
        o = filled[derivative_of[s]]
        width = savgol_window(o, dt) if window_s is None else _odd_window(round(window_s / dt), o.shape[1])
        filled[s] = savgol_derivative(o, dt, width)
        estimated[s] = (
            f"Savitzky–Golay derivative of {derivative_of[s]}, window {width} samples ({width * dt:.3g} s), "
            f"polyorder {POLYORDER}"
        )
        freq = dominant_frequency(o, dt)
        gain = savgol_gain(width, freq * dt) if freq > 0 else 1.0
        if gain < MIN_GAIN and window_s is None:
            narrow[s] = (
                f"its Savitzky–Golay derivative of {derivative_of[s]} ({width} samples) has a gain of {gain:.2f} at "
                f"the signal's dominant frequency {freq:.4g} Hz ({1 / (freq * dt):.3g} samples a period)"
            )
    if narrow and model_based:
        pending = [*pending, *narrow]
        latent = [s for s in latent if s not in narrow]
    new_x = torch.stack([filled[s] for s in order], dim=-1).to(data.x.dtype)
    derived = {s: derivative_of[s] for s in latent}
    estimated.update({s: "pending: the model-based estimate" for s in pending})
    for s, why in narrow.items():
        estimated[s] = f"{estimated[s]}; {why}" if s in pending else f"{estimated[s]} ({why}: biased)"
    meta = {**data.meta, "state_names": order, "observed": observed, "estimated": estimated, "derived_from": derived}
    if pending:
        meta["pending"] = list(pending)
        meta["pending_why"] = {s: narrow.get(s, "no measured state is its rate") for s in pending}
    return replace(data, x=new_x, meta=meta)


def dominant_frequency(o: torch.Tensor, dt: float) -> float:  # o: [B, T, N] a measured state
    """The frequency (Hz) of the largest peak of `o`'s periodogram (each trajectory and node detrended, their
    spectra summed), or 0 for a record too short to have one."""
    x = o.double().movedim(1, -1)  # [B, N, T]
    n = x.shape[-1]
    if n < 8:
        return 0.0
    t = torch.arange(n, dtype=x.dtype)
    slope = ((t - t.mean()) * (x - x.mean(-1, keepdim=True))).sum(-1, keepdim=True) / ((t - t.mean()) ** 2).sum()
    detrended = x - x.mean(-1, keepdim=True) - slope * (t - t.mean())
    power = torch.fft.rfft(detrended * torch.hann_window(n, periodic=False, dtype=x.dtype)).abs().pow(2)
    spectrum = power.reshape(-1, power.shape[-1]).sum(0)
    k = int(spectrum[1:].argmax()) + 1
    return k / (n * dt)


def savgol_gain(width: int, cycles_per_sample: float) -> float:
    """The gain of the Savitzky–Golay derivative (order `POLYORDER`, `width` samples) at a sine of
    `cycles_per_sample` (f·dt): the amplitude it gives over the true derivative's (1: exact, < 1: it flattens)."""
    from scipy.signal import savgol_coeffs

    if width < 3 or cycles_per_sample <= 0:
        return 1.0
    coeffs = savgol_coeffs(width, min(POLYORDER, width - 1), deriv=1, delta=1.0, use="dot")
    k = np.arange(width) - width // 2
    w = 2 * np.pi * cycles_per_sample
    response = np.abs(np.sum(coeffs * np.exp(1j * w * k)))
    return float(response / w)


def _check_names(data: Trajectories, derivative_of: Mapping[str, str], observed: list[str], order: list[str]) -> None:
    source = data.meta.get("source", "data")
    for s in order:
        if s in observed:
            continue
        o = derivative_of.get(s)
        if o is None:
            raise DataError(
                f"{source}: state '{s}' is not measured (data.observed={observed}) and no equation of the model is "
                f"x' = {s} for a measured x, so it cannot be estimated. Add '{s}' to data.observed (and map its "
                "column with data.columns), or measure the state it is the rate of."
            )
        if o not in observed:
            raise DataError(
                f"{source}: state '{s}' would be estimated as the derivative of '{o}' ({o}' = {s}), but '{o}' is not "
                f"measured either (data.observed={observed}). Add '{o}' to data.observed."
            )


def savgol_derivative(o: torch.Tensor, dt: float, width: int) -> torch.Tensor:  # o: [B, T, N] -> [B, T, N]
    """The Savitzky–Golay (order `POLYORDER`) derivative of `o` along time, `width` samples wide; the ends use the
    polynomial fitted to the first and last windows."""
    from scipy.signal import savgol_filter

    polyorder = min(POLYORDER, width - 1)
    values = savgol_filter(o.numpy(), width, polyorder, deriv=1, delta=dt, axis=1, mode="interp")
    return torch.from_numpy(np.ascontiguousarray(values))


def savgol_window(o: torch.Tensor, dt: float) -> int:  # o: [B, T, N] a measured state
    """The odd window (samples) of the module docstring's rule: the lag in which `o` moves `STEPS_PER_WINDOW`
    resolution steps, at least `MIN_WINDOW`, at most the trajectory's length."""
    x = o.double()[..., None]  # [B, T, N, 1]
    step = grid_quantum(x) or 0.0
    noise = float(noise_level(x)[0])
    delta = max(step, np.sqrt(12.0) * noise)
    target = STEPS_PER_WINDOW * delta
    n_times = x.shape[1]

    def moved(j: int) -> float:
        return float((x[:, j:] - x[:, :-j]).abs().mean())

    high = 1
    while high < n_times - 1 and moved(high) < target:
        high = min(2 * high, n_times - 1)
    low = max(1, high // 2)
    while high - low > 1:  # the shortest lag that reaches the target, between low and high
        mid = (low + high) // 2
        low, high = (mid, high) if moved(mid) < target else (low, mid)
    return _odd_window(high, n_times)


def _odd_window(width: int, n_times: int) -> int:
    """`width` made odd, at least `MIN_WINDOW` (or the longest odd length that fits), at most `n_times`."""
    width = max(width, MIN_WINDOW)
    width += 1 - width % 2
    largest = n_times if n_times % 2 else n_times - 1
    return max(min(width, largest), 1)
