"""The input signal of a driven twin (`system=equations` with `inputs:` in its spec): `system.input`.

One mapping drives every input of the spec (each input, node and trajectory its own realisation), or a mapping
per input name (`input: {tau: {...}, f: {...}}`, all with the same `hold`). Every signal is defined on the
sample grid and held between samples by `hold`, which the data record (`meta["input_hold"]`) and the simulation
integrates exactly (zoh: the solver never steps across a jump).

    input: {kind: multisine, band: [0.1, 2.0], components: 8, rms: 1.0}   # random phases
    input: {kind: steps, levels: [-1, 1], duration: [0.5, 2.0]}           # random levels, random durations
    input: {kind: chirp, f0: 0.1, f1: 2.0, amplitude: 1.0}                # linear sweep over the record
    input: {kind: prbs, amplitude: 1.0, clock: 0.05, sequence: mls}       # ± amplitude; mls | random
    input: {file: excitation.csv, column: u}                              # a recorded signal (time column t)

Keys of every kind: `hold` (zoh | linear, default zoh), `seed` (default 0), `offset` (added, default 0).
Realisations are reproducible: trajectory b of a dataset drawn with seed s gets the same signal for the same
`input.seed` (the train, validation and test splits, drawn with different seeds, get different ones).

- multisine: `components` cosines (default 8) at frequencies spaced evenly over `band` [f_lo, f_hi] (Hz, in
  the system's time unit; default [0.1, 1.0]) with uniformly random phases; each of amplitude `amplitude`, or
  all scaled to the RMS `rms` (default 1.0; give one of the two).
- steps: levels uniform in `levels` [lo, hi] (default [-1, 1]), each held for a duration uniform in `duration`
  [d_min, d_max] (default 5–20 % of the record), switching at the first sample at or after its time.
- chirp: amplitude · sin(2π(f0·τ + (f1 − f0)·τ²/(2L)) + φ), τ the time since the record's start, L its length,
  φ a random phase (`f0` default 0.1, `f1` default 1.0, `amplitude` default 1).
- prbs: ± `amplitude` (default 1), switching only at multiples of the `clock` period (default: the sample
  step); `sequence: mls` (default) reads a maximal-length LFSR sequence from a random start (one shift per
  realisation), `random` draws each bit independently.
- file: the CSV's column `column` (default: the input's name) against its time column `time_column` (default
  t), sampled at the simulation's times by `hold` (zoh: the file's sample at or before; linear: interpolated).
  The same signal drives every trajectory and node; it must cover the whole record. A relative path is read
  from the current directory, which on the command line is the directory mpsim was started from. At most
  `INPUT_FILE_BYTES` (512 MB) are read; the file is only read (its path is checked to be a regular file first).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mpsim.errors import ConfigError, did_you_mean
from mpsim.safeload import not_a_regular_file, size_text
from mpsim.signals import HOLDS

KINDS = ("multisine", "steps", "chirp", "prbs", "file")
#: the largest input file read (a CSV of a few columns: tens of millions of samples)
INPUT_FILE_BYTES = 512 * 2**20
COMMON = ("kind", "hold", "seed", "offset")
KEYS = {
    "multisine": ("band", "components", "amplitude", "rms"),
    "steps": ("levels", "duration"),
    "chirp": ("f0", "f1", "amplitude"),
    "prbs": ("amplitude", "clock", "sequence"),
    "file": ("file", "column", "time_column"),
}
#: feedback taps (1-based bit positions) of a maximal-length Fibonacci LFSR of each order (Xilinx XAPP 052)
MLS_TAPS = {
    2: (2, 1),
    3: (3, 2),
    4: (4, 3),
    5: (5, 3),
    6: (6, 5),
    7: (7, 6),
    8: (8, 6, 5, 4),
    9: (9, 5),
    10: (10, 7),
    11: (11, 9),
    12: (12, 6, 4, 1),
    13: (13, 4, 3, 1),
    14: (14, 5, 3, 1),
    15: (15, 14),
    16: (16, 15, 13, 4),
    17: (17, 14),
    18: (18, 11),
    19: (19, 6, 2, 1),
    20: (20, 17),
    21: (21, 19),
    22: (22, 21),
    23: (23, 18),
    24: (24, 23, 22, 17),
}


def _number(value: Any, where: str, positive: bool = False) -> float:
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or (positive and value <= 0):
        raise ConfigError(f"{where} must be a {'positive ' if positive else ''}finite number; got {value!r}.")
    return float(value)


def _pair(value: Any, where: str, positive: bool = False) -> tuple[float, float]:
    if isinstance(value, str) or not isinstance(value, Sequence) or len(value) != 2:
        raise ConfigError(f"{where} must be [low, high]; got {value!r}.")
    lo, hi = (_number(v, where, positive) for v in value)
    if lo > hi:
        raise ConfigError(f"{where} must be [low, high] with low <= high; got {list(value)}.")
    return lo, hi


class Signal:
    """One input's signal generator, checked from its config mapping (see the module docstring).

    Args:
        config: the mapping (`kind` and its keys, or `file` and `column`).
        name: the input it drives (the default column of a file).
        where: the config key, for messages (e.g. ``system.input``).
    """

    def __init__(self, config: Mapping[str, Any], name: str, where: str) -> None:
        kind = config.get("kind", "file" if "file" in config else None)
        if kind not in KINDS:
            hint = did_you_mean(str(kind), KINDS) if kind is not None else ""
            raise ConfigError(
                f"{where}.kind={kind!r} is not a signal.{hint} Choose one of {', '.join(KINDS)} "
                "(or give file: <path.csv> with column: <name>)."
            )
        allowed = (*COMMON, *KEYS[kind])
        for key in config:
            if key not in allowed:
                raise ConfigError(
                    f"{where}.{key} is not a key of a {kind} signal.{did_you_mean(str(key), allowed)} "
                    f"Keys: {', '.join(allowed)}."
                )
        self.kind, self.name, self.where, self.config = kind, name, where, dict(config)
        self.hold = config.get("hold", "zoh")
        if self.hold not in HOLDS:
            raise ConfigError(f"{where}.hold={self.hold!r}: use zoh (each sample held) or linear (interpolated).")
        seed = config.get("seed", 0)
        if not isinstance(seed, int) or isinstance(seed, bool):
            raise ConfigError(f"{where}.seed must be an integer; got {seed!r}.")
        self.seed = seed
        self.offset = _number(config.get("offset", 0.0), f"{where}.offset")
        self._check()
        self.recording: tuple[np.ndarray, np.ndarray] | None = None  # (t, u) of a file, read once

    def _check(self) -> None:
        """Check the kind's own keys now, before anything is simulated."""
        c, w = self.config, self.where
        if self.kind == "multisine":
            _pair(c.get("band", [0.1, 1.0]), f"{w}.band", positive=True)
            k = c.get("components", 8)
            if not isinstance(k, int) or isinstance(k, bool) or not 1 <= k <= 10_000:
                raise ConfigError(f"{w}.components must be an integer from 1 to 10000; got {k!r}.")
            if c.get("amplitude") is not None and c.get("rms") is not None:
                raise ConfigError(f"{w}: give amplitude (of each component) or rms (of the sum), not both.")
            for key in ("amplitude", "rms"):
                if c.get(key) is not None:
                    _number(c[key], f"{w}.{key}", positive=True)
        elif self.kind == "steps":
            _pair(c.get("levels", [-1.0, 1.0]), f"{w}.levels")
            if c.get("duration") is not None:
                _pair(c["duration"], f"{w}.duration", positive=True)
        elif self.kind == "chirp":
            for key, default in (("f0", 0.1), ("f1", 1.0), ("amplitude", 1.0)):
                _number(c.get(key, default), f"{w}.{key}", positive=key == "amplitude")
        elif self.kind == "prbs":
            _number(c.get("amplitude", 1.0), f"{w}.amplitude", positive=True)
            if c.get("clock") is not None:
                _number(c["clock"], f"{w}.clock", positive=True)
            if c.get("sequence", "mls") not in ("mls", "random"):
                raise ConfigError(f"{w}.sequence={c.get('sequence')!r}: use mls (maximal length) or random.")
        else:
            if not isinstance(c.get("file"), str | Path) or not str(c.get("file")).strip():
                raise ConfigError(f"{w}.file must be the path of a CSV file; got {c.get('file')!r}.")
            for key in ("column", "time_column"):
                if c.get(key) is not None and not isinstance(c[key], str):
                    raise ConfigError(f"{w}.{key} must be a column name; got {c[key]!r}.")

    def sample(
        self,
        t: torch.Tensor,  # [T] sample times (float64)
        shape: tuple[int, int],  # (B, N) realisations
        generator: torch.Generator,
    ) -> torch.Tensor:
        """[B, T, N] float64 the signal at the sample times, one realisation per trajectory and node."""
        draw = {
            "multisine": _multisine,
            "steps": _steps,
            "chirp": _chirp,
            "prbs": _prbs,
        }.get(self.kind)
        if draw is None:
            u = self._from_file(t).expand(shape[0], shape[1], -1)
        else:
            u = draw(self.config, t, shape[0] * shape[1], generator).reshape(*shape, -1)
        return u.permute(0, 2, 1).contiguous() + self.offset

    def _from_file(self, t: torch.Tensor) -> torch.Tensor:  # t: [T] sample times
        """[T] the file's column at the sample times (zoh: its sample at or before; linear: interpolated)."""
        if self.recording is None:
            self.recording = read_signal_file(
                self.config["file"],
                self.config.get("column") or self.name,
                self.config.get("time_column") or "t",
                self.where,
            )
        tf, uf = self.recording
        times = t.numpy()
        tol = 1e-9 * max(1.0, float(np.abs(tf).max()))
        if times[0] < tf[0] - tol or times[-1] > tf[-1] + tol:
            raise ConfigError(
                f"{self.where}.file {self.config['file']} covers t = {tf[0]:g} to {tf[-1]:g} but the simulation "
                f"runs from {times[0]:g} to {times[-1]:g}; shorten the record (data.horizon, data.dt) or give a "
                "longer signal."
            )
        if self.hold == "linear":
            return torch.from_numpy(np.interp(times, tf, uf))
        k = np.clip(np.searchsorted(tf, times + tol, side="right") - 1, 0, len(tf) - 1)
        return torch.from_numpy(uf[k].copy())


def read_signal_file(path: str | Path, column: str, time_column: str, where: str) -> tuple[np.ndarray, np.ndarray]:
    """(t [K], u [K]) float64 from a CSV's time column and `column` (strictly increasing, finite numbers).

    Raises:
        ConfigError: the file is missing or unreadable, lacks a column, or holds non-numbers, gaps or unsorted times.
    """
    import pandas as pd

    path = Path(path).expanduser()
    why = not_a_regular_file(path)
    if why is not None:
        raise ConfigError(
            f"{where}.file: {path} {why}; give the path of a CSV file with columns {time_column}, {column}."
        )
    size = path.stat().st_size
    if size > INPUT_FILE_BYTES:
        raise ConfigError(
            f"{where}.file: {path} is {size_text(size)}, more than the {size_text(INPUT_FILE_BYTES)} mpsim reads as an "
            "input signal; keep only the time and input columns, or resample it."
        )
    try:
        frame = pd.read_csv(path)
    except Exception as err:  # noqa: BLE001 - pandas raises many kinds for a bad file; one message for all
        raise ConfigError(f"{where}.file: cannot read {path} as CSV ({type(err).__name__}: {err}).") from None
    columns = [str(c) for c in frame.columns]
    for name in (time_column, column):
        if name not in columns:
            raise ConfigError(
                f"{where}.file: {path} has no column {name!r}.{did_you_mean(name, columns)} Columns: {columns}; "
                f"set {where}.column (the signal) and {where}.time_column (default t)."
            )
    values = []
    for name in (time_column, column):
        v = pd.to_numeric(frame[name], errors="coerce").to_numpy(dtype=np.float64)
        bad = ~np.isfinite(v)
        if bad.any():
            row = int(np.nonzero(bad)[0][0])
            cell = frame[name].iloc[row]
            what = "is empty" if pd.isna(cell) else f"holds {str(cell)!r}, not a finite number"
            raise ConfigError(
                f"{where}.file: {path}, row {row + 2}, column {name!r} {what}. Fill in or remove that row."
            )
        values.append(v)
    tf, uf = values
    if len(tf) < 2 or bool((np.diff(tf) <= 0).any()):
        raise ConfigError(
            f"{where}.file: {path} needs at least 2 rows with strictly increasing {time_column!r}; sort it by time "
            "and drop repeated times."
        )
    return tf, uf


# ---- generators: [M, T] realisations at the sample times t [T] ----------------------------------------------
def _multisine(c: Mapping[str, Any], t: torch.Tensor, m: int, gen: torch.Generator) -> torch.Tensor:
    lo, hi = c.get("band", [0.1, 1.0])
    k = int(c.get("components", 8))
    freqs = torch.linspace(float(lo), float(hi), k, dtype=torch.float64)  # [K]
    phases = 2 * math.pi * torch.rand(m, k, 1, generator=gen, dtype=torch.float64)
    amp = float(c["amplitude"]) if c.get("amplitude") is not None else float(c.get("rms") or 1.0) * math.sqrt(2 / k)
    return amp * torch.cos(2 * math.pi * freqs[None, :, None] * t[None, None, :] + phases).sum(1)


def _steps(c: Mapping[str, Any], t: torch.Tensor, m: int, gen: torch.Generator) -> torch.Tensor:
    length = float(t[-1] - t[0])
    lo_d, hi_d = c.get("duration") or (0.05 * length, 0.2 * length)
    lo_d = max(float(lo_d), 1e-12)
    n_levels = min(t.numel(), math.ceil(length / lo_d) + 1)  # enough switches to cover the record
    durations = lo_d + (float(hi_d) - lo_d) * torch.rand(m, n_levels, generator=gen, dtype=torch.float64)
    switches = t[0] + durations.cumsum(1)  # [M, L] the end of each level
    lo, hi = c.get("levels", [-1.0, 1.0])
    levels = float(lo) + (float(hi) - float(lo)) * torch.rand(m, n_levels + 1, generator=gen, dtype=torch.float64)
    index = torch.searchsorted(switches, t[None, :].expand(m, -1).contiguous(), right=True)  # [M, T]
    return levels.gather(1, index)


def _chirp(c: Mapping[str, Any], t: torch.Tensor, m: int, gen: torch.Generator) -> torch.Tensor:
    f0, f1, amp = float(c.get("f0", 0.1)), float(c.get("f1", 1.0)), float(c.get("amplitude", 1.0))
    tau = t - t[0]
    span = float(tau[-1]) if float(tau[-1]) > 0 else 1.0
    phase = 2 * math.pi * (f0 * tau + (f1 - f0) * tau**2 / (2 * span))  # [T]
    start = 2 * math.pi * torch.rand(m, 1, generator=gen, dtype=torch.float64)
    return amp * torch.sin(phase[None, :] + start)


def _prbs(c: Mapping[str, Any], t: torch.Tensor, m: int, gen: torch.Generator) -> torch.Tensor:
    amp = float(c.get("amplitude", 1.0))
    step = float(t[1] - t[0]) if t.numel() > 1 else 1.0
    clock = float(c.get("clock") or step)
    period = torch.floor((t - t[0]) / clock + 1e-9).long()  # [T] clock period of each sample
    n_bits = int(period[-1]) + 1
    if c.get("sequence", "mls") == "random":
        bits = torch.randint(0, 2, (m, n_bits), generator=gen)
    else:
        bits = _mls_bits(n_bits, m, gen)
    return amp * (2.0 * bits.gather(1, period[None, :].expand(m, -1)).double() - 1.0)


def _mls_bits(n_bits: int, m: int, gen: torch.Generator, order: int | None = None) -> torch.Tensor:
    """[M, n_bits] 0/1 bits of a maximal-length LFSR sequence (`order` default: the smallest whose period
    2^order − 1 covers n_bits, at least 2), each row from a random nonzero start state."""
    order = max(2, math.ceil(math.log2(n_bits + 1))) if order is None else order
    if order not in MLS_TAPS:
        raise ConfigError(
            f"a maximal-length sequence of {n_bits} clock periods needs an LFSR of order {order} (mpsim has up to "
            f"{max(MLS_TAPS)}); use a longer clock or sequence: random."
        )
    state = torch.randint(1, 2**order, (m,), generator=gen)  # [M] nonzero start states
    taps = MLS_TAPS[order]
    out = torch.empty(m, n_bits, dtype=torch.long)
    for i in range(n_bits):  # sequential in time only; every realisation at once
        out[:, i] = state & 1
        feedback = torch.zeros_like(state)
        for tap in taps:
            feedback ^= (state >> (order - tap)) & 1
        state = (state >> 1) | (feedback << (order - 1))
    return out


# ---- the input of a driven twin --------------------------------------------------------------------------
class InputSignals:
    """The signals of every input of a spec (`system.input`), with their common hold.

    Args:
        config: one signal mapping for every input, or a mapping input name -> signal mapping.
        inputs: the spec's input names.
        where: the config key, for messages.
    """

    def __init__(self, config: Any, inputs: Sequence[str], where: str = "system.input") -> None:
        if not isinstance(config, Mapping):
            raise ConfigError(
                f"{where} must be a mapping, e.g. {{kind: multisine, band: [0.1, 2.0]}} or {{file: u.csv, column: u}}; "
                f"got {config!r}."
            )
        if config and all(k in inputs for k in config):
            missing = [n for n in inputs if n not in config]
            if missing:
                raise ConfigError(f"{where} gives signals for {list(config)} but not for the inputs {missing}.")
            self.signals = [Signal(_mapping(config[n], f"{where}.{n}"), n, f"{where}.{n}") for n in inputs]
        else:
            self.signals = [Signal(config, n, where) for n in inputs]
            if len(inputs) > 1 and self.signals[0].kind == "file" and config.get("column") is not None:
                raise ConfigError(
                    f"{where}.column names one column but the spec has the inputs {list(inputs)}; leave column out "
                    f"(each input reads the column of its name) or give {where}.<input>: {{file: ..., column: ...}}."
                )
        holds = {s.hold for s in self.signals}
        if len(holds) > 1:
            raise ConfigError(f"{where}: the inputs' holds differ ({sorted(holds)}); one dataset has one hold.")
        self.hold = holds.pop()

    def sample(
        self,
        t: torch.Tensor,  # [T] sample times
        n: int,  # B trajectories
        n_nodes: int,  # N nodes
        seed: int,  # the dataset's seed (with each signal's own seed)
    ) -> torch.Tensor:
        """[B, T, N, C] float64 inputs, reproducible from (`seed`, each signal's `seed`)."""
        t = t.detach().double().cpu()
        out = []
        for c, signal in enumerate(self.signals):  # a loop over the spec's few inputs
            gen = torch.Generator().manual_seed((int(seed) * 1_000_003 + signal.seed * 7919 + c) % (2**63))
            out.append(signal.sample(t, (n, n_nodes), gen))
        return torch.stack(out, dim=-1)


def _mapping(value: Any, where: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise ConfigError(f"{where} must be a signal mapping such as {{kind: multisine}}; got {value!r}.")
    return value
