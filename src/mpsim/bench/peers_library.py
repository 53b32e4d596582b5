"""PySINDy's side of `mpsim bench bench=peers` (issue 61): its target, its library, its sparse fit.

The library is the loop's kinds extended the way an exploring PySINDy user extends a library (see `peers.py`'s
docstring for the whole rule): state terms, neighbour sums at harmonics 1-3, a drive at the residual's periodogram
peak, delayed copies on the sampling grid, t-modulated terms and t-modulated nominal terms. Each column keeps the
name mpsim would give the same term, so that both tools are judged by one rule.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from mpsim import effects as fx
from mpsim.data.trajectories import Trajectories
from mpsim.diagnose.library import DRY_MIN_SCALE, evaluate_effect
from mpsim.diagnose.noise import resolution
from mpsim.errors import ConfigError
from mpsim.graphs.batch import batch_graph
from mpsim.models.equations import EquationsModel

INSTALL = "pip install 'mpsim[peers]'"
#: per-state kinds (one column of each state s), and the kinds that need a graph
STATE_KINDS = ("LinearDamping", "QuadraticDrag", "CubicStiffness", "DryFriction")
COUPLINGS = ("DiffusiveCoupling", "SineCoupling", "CosineCoupling")
#: harmonics k of the phase couplings: Σ_j sin/cos(k(s_j − s_i))
HARMONICS = (1, 2, 3)
#: delayed copies s(t − m·dt): PySINDy sees a delay only on the sampling grid (the loop's default delays too)
DELAY_STEPS = (1, 2, 4, 8)
#: the families the exploring user adds to the loop's kinds (`bench.extend`; [] is the loop's library less
#: DelayedFeedback and ParameterDrift, first harmonics only)
EXTENSIONS = ("delays", "time", "harmonics")
#: a unit-RMS column whose part outside the span of the earlier columns has less RMS than this is left out: the
#: earlier columns already hold it (a drifting stiffness's t·k·x is −k × t·(−x); on a linear system the delayed
#: copies are exact linear maps of the current state, x(t − τ) = e^{−Aτ}x(t))
DEPENDENT = 1e-5
#: relative step of the central difference p·∂f/∂p ≈ (f(p(1 + h)) − f(p(1 − h))) / 2h (exact for linear p)
DRIFT_STEP = 1e-5


@dataclass
class Column:
    """One library term.

    Attributes:
        kind: the scorecard's kind name ("SineCoupling(k=2)", "DelayedFeedback", "t·LinearDamping", ...).
        name: the term as mpsim labels it ("DelayedFeedback(v, τ=0.2)").
        params: the fixed values reported with the coefficient (omega of a drive, delay of a feedback).
        values: [B, T, N, K] the term at every observed state and time (K = 2: a drive's sin and cos).
    """

    kind: str
    name: str
    params: dict[str, float]
    values: np.ndarray


def require_pysindy() -> Any:
    """The `pysindy` module, or one clear message naming the extra that installs it."""
    try:
        import pysindy  # type: ignore[import-not-found, import-untyped, unused-ignore]
    except ImportError:
        raise ConfigError(
            f"bench=peers runs PySINDy beside mpsim, and pysindy is not installed: {INSTALL} "
            "(or pip install 'pysindy>=2')."
        ) from None
    return pysindy


@torch.no_grad()
def nominal_rhs(model: EquationsModel, data: Trajectories, values: dict[str, torch.Tensor] | None = None) -> np.ndarray:
    """[B, T, N, D] the nominal model's right-hand side at every observed state and time (`values`: the
    parameters to use, default the model's own)."""
    b, n_t, n, d = data.x.shape
    x = data.x.double().reshape(b * n_t, n, d)
    t = data.t.double()[None, :].expand(b, n_t).reshape(b * n_t, 1)
    ei = data.edge_index if data.shared_graph else data.edge_index.repeat_interleave(n_t, dim=0)
    graph = batch_graph(ei, b * n_t, n, dtype=torch.float64) if data.edge_index.numel() else None
    if values is None:
        values = {k: v.detach().double() for k, v in model.parameters_now().items()}
    return model.field(t, x, values, graph).reshape(b, n_t, n, d).numpy()


def periodogram_peak(r: np.ndarray, t: np.ndarray, pad: int = 16) -> float:  # r: [B, T, N] residual; t: [T]
    """Angular frequency of the peak of the mean per-recording periodogram of r (node-averaged)."""
    signal = r.mean(axis=2)
    signal = signal - signal.mean(axis=1, keepdims=True)
    n_t = signal.shape[1]
    power = np.abs(np.fft.rfft(signal * np.hanning(n_t), n=pad * n_t, axis=1)) ** 2
    freqs = 2 * math.pi * np.fft.rfftfreq(pad * n_t, d=float(t[1] - t[0]))
    lowest = 2 * pad  # skip the window's main lobe at zero frequency (as the loop does)
    return float(freqs[lowest + int(np.argmax(power.mean(axis=0)[lowest:]))])


def _effect(data: Trajectories, effect: fx.Effect) -> np.ndarray:
    """[B, T, N, K] an effect's own features (its signs and units) on `data`."""
    return evaluate_effect(effect.bind(data.state_names), data).detach().numpy()


def state_columns(data: Trajectories, extend: tuple[str, ...] = EXTENSIONS) -> list[Column]:
    """The terms that do not depend on the row: Bias; −s, −s|s|, −s³, −tanh(s/ε) per state; the neighbour sums
    Σ_j(s_j − s_i), Σ_j sin/cos(k(s_j − s_i)) (k = 1, 2, 3 with "harmonics" in `extend`, else 1) on a graph;
    with "delays", delayed copies s(t − m·dt) (constant history before t0: those samples are not fitted)."""
    names, d = list(data.state_names), data.state_dim
    has_edges = data.edge_index.numel() > 0 and bool((data.edge_index >= 0).any())
    eps = torch.maximum(resolution(data.x), DRY_MIN_SCALE * data.x.double().reshape(-1, d).std(0))
    out = [Column("Bias", "Bias", {}, _effect(data, fx.Bias(0.0, target=0)))]
    for kind in STATE_KINDS:
        for s in range(d):
            extra = {"scale": float(eps[s])} if kind == "DryFriction" else {}
            effect = getattr(fx, kind)(0.0, target=0, source=s, **extra)
            out.append(Column(kind, f"{kind}({names[s]})", {}, _effect(data, effect)))
    for kind in COUPLINGS if has_edges else ():
        for s in range(d):
            for k in HARMONICS if kind != "DiffusiveCoupling" and "harmonics" in extend else (1,):
                extra = {"harmonic": k} if k > 1 else {}
                label, inside = (f"{kind}(k={k})", f"{names[s]}, k={k}") if k > 1 else (kind, names[s])
                effect = getattr(fx, kind)(0.0, target=0, source=s, **extra)
                out.append(Column(label, f"{kind}({inside})", {}, _effect(data, effect)))
    x, dt = data.x.double().numpy(), float(data.t[1] - data.t[0])
    for m in (m for m in DELAY_STEPS if m < data.n_times - 1 and "delays" in extend):
        past = np.concatenate([np.repeat(x[:, :1], m, axis=1), x[:, :-m]], axis=1)  # [B, T, N, D]
        for s in range(d):
            name = f"DelayedFeedback({names[s]}, τ={m * dt:.4g})"
            out.append(Column("DelayedFeedback", name, {"delay": m * dt}, past[..., s : s + 1]))
    return out


def timed_columns(data: Trajectories, columns: list[Column]) -> list[Column]:
    """t times each of the columns' Bias and per-state terms: t, −t·s, −t·s|s|, −t·s³, −t·tanh(s/ε)."""
    t = data.t.double().numpy()[None, :, None, None]  # [1, T, 1, 1]
    timed = [c for c in columns if c.kind in ("Bias", *STATE_KINDS)]
    return [Column(f"t·{c.kind}", f"t·{c.name}", {}, t * c.values) for c in timed]


def row_columns(
    model: EquationsModel,
    data: Trajectories,
    row: int,
    omega: float,
    rhs: np.ndarray,  # [B, T, N, D] the nominal right-hand side
    time: bool = True,
) -> list[Column]:
    """The terms of one row: the drive sin ωt, cos ωt; with `time`, the drift t·p·∂f_row/∂p of each learnable
    scalar p of the nominal model (`ParameterDrift(p)`, coefficient the rate s of p·(1 + s·t)) and t·f_row."""
    drive = fx.PeriodicForcing(0.0, omega=omega, target=0)
    out = [Column("PeriodicForcing", f"PeriodicForcing(ω={omega:.4g})", {"omega": omega}, _effect(data, drive))]
    if not time:
        return out
    t = data.t.double().numpy()[None, :, None, None]  # [1, T, 1, 1]
    values = {k: v.detach().double() for k, v in model.parameters_now().items()}
    for p in (p for p in model.raw if values[p].dim() == 0):  # the spec's few learnable scalars
        up = nominal_rhs(model, data, {**values, p: values[p] * (1 + DRIFT_STEP)})
        down = nominal_rhs(model, data, {**values, p: values[p] * (1 - DRIFT_STEP)})
        sens = (up - down)[..., row : row + 1] / (2 * DRIFT_STEP)  # [B, T, N, 1] p·∂f_row/∂p
        out.append(Column("ParameterDrift", f"ParameterDrift({p})", {}, t * sens))
    name = data.state_names[row]
    return out + [Column("t·f", f"t·f_{name} (the nominal right-hand side)", {}, t * rhs[..., row : row + 1])]


def sparse_fit(ps: Any, columns: list[Column], y: np.ndarray, threshold: float, row: str) -> list[dict[str, Any]]:
    """STLSQ of y: [M] on the columns (each [M, K] flattened, scaled to unit RMS); the kept terms, named.

    A column that is all zero (a graph sum without edges) or a linear combination of the earlier ones
    (`DEPENDENT`, from the diagonal of a QR factorisation in library order) is left out before the fit."""
    blocks = [c.values.reshape(y.size, -1) for c in columns]
    theta = np.concatenate(blocks, axis=1)  # [M, K]
    scale = np.sqrt((theta**2).mean(axis=0))
    nonzero = scale > 1e-12 * max(float(scale.max()), 1e-300)
    unit = theta / np.where(nonzero, scale, 1.0)
    outside = np.abs(np.diag(np.linalg.qr(unit, mode="r"))) / math.sqrt(y.size)  # [K] RMS beyond earlier columns
    usable = nonzero & (outside > DEPENDENT)
    opt = ps.STLSQ(threshold=threshold)
    with warnings.catch_warnings():  # "eliminated all coefficients" is PySINDy's no-claim, reported as such
        warnings.simplefilter("ignore", UserWarning)
        opt.fit(unit[:, usable], y[:, None])
    coef = np.zeros(theta.shape[1])
    coef[usable] = opt.coef_[0] / scale[usable]
    named, start = [], 0
    for col, block in zip(columns, blocks, strict=True):
        c = coef[start : start + block.shape[1]]
        start += block.shape[1]
        if not np.any(c != 0):
            continue
        if len(c) == 2:
            values = {"amplitude": float(np.hypot(*c)), **col.params}
        else:
            values = {("s" if col.kind == "ParameterDrift" else "coef"): float(c[0]), **col.params}
        named.append({"kind": col.kind, "row": row, "label": f"d{row}/dt: {col.name}", "values": values})
    return named


def pysindy_side(
    data: Trajectories, model: EquationsModel, threshold: float = 0.05, extend: tuple[str, ...] = EXTENSIONS
) -> tuple[list[dict], float]:
    """(the terms PySINDy names on the dynamic rows, its wall time in seconds) for `data` and the nominal `model`
    (`peers.py`'s docstring: target, library, threshold rule; `extend`: the families added to the loop's kinds,
    `EXTENSIONS`). With delays, the first max(DELAY_STEPS) samples of every
    recording, which have no delayed copy, are left out of the fit."""
    ps = require_pysindy()
    start = time.perf_counter()
    b, n_t, n, d = data.x.shape
    x, t = data.x.double().numpy(), data.t.double().numpy()
    xdot = ps.FiniteDifference(axis=1)(x.reshape(b, n_t, n * d), t).reshape(b, n_t, n, d)
    rhs = nominal_rhs(model, data)
    residual = xdot - rhs
    shared = state_columns(data, extend)
    timed = timed_columns(data, shared) if "time" in extend else []
    first = max((m for m in DELAY_STEPS if m < n_t - 1 and "delays" in extend), default=0)
    named: list[dict] = []
    for i, row in enumerate(data.state_names):
        if row in model.kinematic_states:
            continue
        # library order matters only for dependent columns (the earlier is kept): drift before t·(−s)
        omega = periodogram_peak(residual[..., i], t)
        columns = shared + row_columns(model, data, i, omega, rhs, "time" in extend) + timed
        kept = [Column(c.kind, c.name, c.params, c.values[:, first:]) for c in columns]
        rule = threshold * float(np.sqrt((xdot[:, first:, :, i] ** 2).mean()))
        named += sparse_fit(ps, kept, residual[:, first:, :, i].reshape(-1), rule, row)
    return named, time.perf_counter() - start
