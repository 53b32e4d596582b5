"""Train/validation/test splits, normalisation statistics and measurement noise.

Simulated splits are drawn from separate seed streams (train 3s, validation 3s+1, test 3s+2 for
`data.seed = s`), so the test set does not change when the training set grows, and a larger training
set extends a smaller one (the first n initial states are the same; the adaptive ground-truth solver
shares its steps across a batch, so trajectories agree to its tolerance).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import torch

from mpsim.data.cache import cached
from mpsim.data.trajectories import Trajectories
from mpsim.errors import ConfigError, DataError

SPLITS = ("train", "val", "test")


class Simulator(Protocol):
    """What `simulate_splits` needs of a ground-truth system (`mpsim.systems.base.System` is one): its default
    sampling step and horizon, and `generate`. Declared here so that data never imports the systems above it."""

    dt: float
    horizon: int

    def generate(
        self,
        n: int,
        seed: int,
        dt: float | None = ...,
        horizon: int | None = ...,
        rtol: float = ...,
        atol: float = ...,
        burn_in: int = ...,  # asked for only when nonzero: some systems do not take it
    ) -> Trajectories: ...


def generate(system: Simulator, n: int, seed: int, **kwargs: Any) -> Trajectories:
    """`system.generate(n, seed, **kwargs)`, with a ground truth that cannot be simulated (the adaptive solver's
    step underflowed, or the states left the floats) reported as one ConfigError naming the system: its
    parameters, the sampling step or the horizon are the user's to change."""
    try:
        return system.generate(n, seed, **kwargs)
    except (AssertionError, DataError) as err:  # torchdiffeq reports a step underflow by `assert`; NaN states
        if isinstance(err, DataError) and "NaN/inf" not in str(err):
            raise
        if isinstance(err, DataError):
            why = "its states became NaN or infinite"
        elif "max_num_steps" in str(err):
            why = f"the ground-truth solver needed too many steps for one sampling interval ({err})"
        else:
            why = f"the ground-truth solver's step size underflowed ({err})"
        raise ConfigError(
            f"cannot simulate {system!r}: {why}. Its dynamics are too stiff or blow up at these settings; check the "
            "system's parameters (system.*) and data.dt (the sampling step, in the system's time units)."
        ) from None


@dataclass
class Splits:
    """The three splits of one dataset; for measured recordings also the test records whole (`records`: [R,
    T_max, N, D], each padded after its end, `mpsim.data.segments.whole_records`), which free-run evaluation
    simulates from start to end."""

    train: Trajectories
    val: Trajectories
    test: Trajectories
    records: Trajectories | None = None

    def sizes(self) -> dict[str, int]:
        return {"train": len(self.train), "val": len(self.val), "test": len(self.test)}


@dataclass(frozen=True)
class DatasetSpec:
    """What a simulated dataset is (every field is part of its cache key).

    Attributes:
        system: the system's full config.
        n_train, n_val, n_test: trajectories per split.
        seed: dataset seed (initial states; the splits use the streams 3·seed, 3·seed + 1, 3·seed + 2).
        dt, horizon: sampling step and steps per trajectory (None: the system's defaults).
        burn_in: steps simulated and discarded before each record (systems' `generate`).
        rtol, atol: ground-truth solver tolerances.
    """

    system: dict[str, Any]
    n_train: int
    n_val: int
    n_test: int
    seed: int = 0
    dt: float | None = None
    horizon: int | None = None
    burn_in: int = 0
    rtol: float = 1e-8
    atol: float = 1e-10


def simulate_splits(system: Simulator, spec: DatasetSpec, cache_dir: str | Path | None = None) -> Splits:
    """Generate (or fetch from the cache) the three splits of the dataset `spec` describes, from `system` (the
    ground truth that `spec.system` configures); `cache_dir` None: no cache."""
    seed, rtol, atol, burn_in = spec.seed, spec.rtol, spec.atol, spec.burn_in
    dt = system.dt if spec.dt is None else float(spec.dt)
    horizon = system.horizon if spec.horizon is None else int(spec.horizon)
    sizes = {"train": spec.n_train, "val": spec.n_val, "test": spec.n_test}
    for name, n in sizes.items():
        if n < 1:
            raise ConfigError(f"data.n_{name} must be >= 1; got {n}.")
    out = {}
    for k, name in enumerate(SPLITS):
        split_seed = 3 * int(seed) + k
        key = {
            "system": spec.system,
            "n": sizes[name],
            "seed": split_seed,
            "dt": dt,
            "horizon": horizon,
            "rtol": rtol,
            "atol": atol,
            **({"burn_in": burn_in} if burn_in else {}),
        }
        extra = {"burn_in": burn_in} if burn_in else {}  # only systems that support it are asked for it
        out[name] = cached(
            cache_dir,
            key,
            functools.partial(
                generate, system, sizes[name], split_seed, dt=dt, horizon=horizon, rtol=rtol, atol=atol, **extra
            ),
        )
    return Splits(**out)


SPLITS = ("train", "val", "test")


def split_sizes(b: int, fractions: Sequence[float], need: tuple[str, ...], what: str) -> list[int] | None:
    """How many of `b` trajectories (or segments: `what`) each of train/val/test gets for the shares `fractions`
    (normalised by their sum): every split with a share gets at least one (3 trajectories split 0.7/0.15/0.15 as
    1/1/1) and the first with a share takes the rounding remainder. None when `b` is too few for that.

    Raises:
        ConfigError: shares that are not three non-negative numbers, or a zero share for a split in `need`.
    """
    if len(fractions) != 3 or any(f < 0 for f in fractions) or sum(fractions) <= 0:
        raise ConfigError(f"data.split must be three non-negative fractions (train, val, test); got {list(fractions)}.")
    empty = [name for name, f in zip(SPLITS, fractions, strict=True) if f == 0 and name in need]
    if empty:  # training stops early on val and reports on test; diagnose fits on train and tests on test
        raise ConfigError(
            f"data.split={list(fractions)} gives the {' and '.join(empty)} split{'s' if len(empty) > 1 else ''} no "
            f"{what}; this command needs {', '.join(need)} with a share > 0 each, e.g. data.split=[0.7,0.15,0.15] "
            f"(shares of the file's {what}, normalised by their sum)."
        )
    total = sum(fractions)
    n = [max(1, int(round(b * f / total))) if f > 0 else 0 for f in fractions]
    first = next(i for i, f in enumerate(fractions) if f > 0)
    n[first] += b - sum(n)
    if any(k < 1 for k, f in zip(n, fractions, strict=True) if f > 0):
        return None
    return n


def split_trajectories(
    data: Trajectories, fractions: Sequence[float], seed: int = 0, need: tuple[str, ...] = SPLITS
) -> Splits:
    """Split loaded data by trajectory with a seeded permutation (`fractions`: shares of train/val/test, normalised).

    The splits in `need` must get a share > 0 and then get at least one trajectory each; the others may have a
    zero share and stay empty (`mpsim eval` needs only test: data.split=[0,0,1] evaluates every trajectory).
    """
    n = split_sizes(len(data), fractions, need, "trajectories")
    if n is None:
        raise DataError(
            f"{data.meta.get('source', 'data')}: {len(data)} trajectories cannot be split into train/val/test "
            f"{list(fractions)} with at least one each; provide at least {sum(f > 0 for f in fractions)} "
            "trajectories or change data.split."
        )
    b = len(data)
    n_train, n_val, _ = n
    order = torch.randperm(b, generator=torch.Generator().manual_seed(int(seed)))
    parts = [order[:n_train], order[n_train : n_train + n_val], order[n_train + n_val :]]
    train, val, test = (_indexed(data, idx) for idx in parts)
    return Splits(train=train, val=val, test=test)


def _indexed(data: Trajectories, idx: torch.Tensor) -> Trajectories:  # idx: [b] trajectory indices
    """The trajectories `idx` of `data`; ``meta['covers']`` says which ("3 of the file's 20 trajectories: 1, 4,
    9", the first dozen named)."""
    part = data.subset(idx)
    numbers = sorted(int(i) for i in idx)
    shown = ", ".join(str(i) for i in numbers[:12]) + (", ..." if len(numbers) > 12 else "")
    text = f"{len(numbers)} of the file's {len(data)} trajectories: {shown}" if numbers else "nothing"
    part.meta = {**part.meta, "covers": text}
    return part


def fit_normalisation(train: Trajectories, min_std: float = 1e-8) -> tuple[torch.Tensor, torch.Tensor]:
    """([D] mean, [D] std) per state feature, pooled over trajectories, times and nodes of the training split.

    A constant feature gets std 1 (it is only centred).
    """
    flat = train.x.double().reshape(-1, train.state_dim)
    mean = flat.mean(0)
    std = flat.std(0) if flat.shape[0] > 1 else torch.ones_like(mean)
    return mean, torch.where(std > min_std, std, torch.ones_like(std))


def add_noise(data: Trajectories, std: torch.Tensor, scale: float, seed: int) -> Trajectories:
    """Copy of `data` with i.i.d. Gaussian noise of `scale`·std (per feature, [D]) added to every state."""
    if scale <= 0:
        return data
    gen = torch.Generator().manual_seed(int(seed) + 7919)
    noise = torch.randn(data.x.shape, generator=gen, dtype=torch.float64) * (scale * std.double())
    return Trajectories(
        t=data.t,
        x=data.x + noise.to(data.x),
        edge_index=data.edge_index,
        u=data.u,
        node_features=data.node_features,
        meta={**data.meta, "noise_std": scale},
    )
