"""`Trajectories`: the one container for simulated and measured data; `Inputs`: the rest of a rollout's input.

Axis letters: B trajectories, T time points, N nodes, D state per node, C control per node, E edges,
F static node features. mpsim is batch-first everywhere; the torchdiffeq boundary (time-first) converts.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, overload

import torch

from mpsim.errors import DataError


@dataclass(frozen=True, eq=False)
class Inputs:
    """What a model's rollout needs beside the states: the graph, controls, node features and metadata.

    Made by `Trajectories.inputs` (or directly, e.g. ``Inputs(chain(3))`` for a graph alone). Immutable; the
    tensors are shared, not copied, and `meta` is the data's own dict (models that merge evaluation passes key on
    its identity).

    Attributes:
        edge_index: [2, E] (sender, receiver) shared by all trajectories, or [B, 2, E] one graph per trajectory,
            padded with -1.
        u: [B, T, N, C] controls on the rollout's time grid (zero-order hold between samples), or None.
        node_features: [N, F] or [B, N, F] static node features (mass, charge, ...), or None.
        meta: the data's metadata (e.g. ``box_size`` of a periodic domain, ``params`` for an energy metric).
        past: [B, P, N, D] recorded states at the P samples before the rollout's first time (same spacing), read
            by delayed effects as their history (None: the history before x0 is x0).
    """

    edge_index: torch.Tensor  # [2, E] shared or [B, 2, E] per-trajectory graph (padded with -1)
    u: torch.Tensor | None = None  # [B, T, N, C] controls
    node_features: torch.Tensor | None = None  # [N, F] or [B, N, F] static node features (mass, charge)
    meta: dict[str, Any] = field(default_factory=dict)
    past: torch.Tensor | None = None  # [B, P, N, D] recorded states before the first time (delays' history)

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Inputs:
        """Move tensors to `device`; cast floating tensors to `dtype` (as `Trajectories.to`); `meta` is kept."""
        return replace(
            self,
            edge_index=self.edge_index.to(device),
            u=_cast(self.u, device, dtype),
            node_features=_cast(self.node_features, device, dtype),
            past=_cast(self.past, device, dtype),
        )


@dataclass
class Trajectories:
    """A batch of trajectories of a graph of identical nodes on one shared time grid.

    Attributes:
        t: [T] time points (strictly increasing, shared by all trajectories).
        x: [B, T, N, D] node states.
        edge_index: [2, E] (sender, receiver) shared by all trajectories, or [B, 2, E] one graph per
            trajectory, padded with -1 where a trajectory has fewer edges.
        u: [B, T, N, C] per-node controls (zero-order hold between samples), or None.
        node_features: [N, F] or [B, N, F] static node features (mass, charge, ...), or None.
        meta: plain JSON-able metadata: ``system`` (name), ``state_names``, ``control_names``, ``dt``,
            ``params`` (the generating system's parameters), plus anything a system records.

    Examples:
        >>> import torch
        >>> from mpsim import Trajectories
        >>> t = torch.linspace(0.0, 1.0, 11)
        >>> x = torch.zeros(4, 11, 3, 2)  # 4 trajectories, 11 times, 3 nodes, 2 states per node
        >>> data = Trajectories(t=t, x=x, edge_index=torch.tensor([[0, 1], [1, 2]]))
        >>> len(data), data.n_times, data.n_nodes, data.state_dim
        (4, 11, 3, 2)
        >>> tuple(data.subset(slice(0, 2)).time_slice(0, 6).x.shape)
        (2, 6, 3, 2)
    """

    t: torch.Tensor
    x: torch.Tensor
    edge_index: torch.Tensor
    u: torch.Tensor | None = None
    node_features: torch.Tensor | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.validate()

    # ---- shape facts ---------------------------------------------------------------------------------
    def __len__(self) -> int:
        return self.x.shape[0]

    @property
    def n_times(self) -> int:
        return self.x.shape[1]

    @property
    def n_nodes(self) -> int:
        return self.x.shape[2]

    @property
    def state_dim(self) -> int:
        return self.x.shape[3]

    @property
    def control_dim(self) -> int:
        return 0 if self.u is None else self.u.shape[3]

    @property
    def shared_graph(self) -> bool:
        return self.edge_index.dim() == 2

    @property
    def state_names(self) -> list[str]:
        names = self.meta.get("state_names")
        return list(names) if names else [f"x{i}" for i in range(self.state_dim)]

    @property
    def observed_index(self) -> list[int]:
        """Indices of the measured state columns: the names in ``meta["observed"]`` (`mpsim.data.latent`), every
        column when the data hold every state (no ``observed`` key). Losses and errors read these columns only; the
        others are latent (estimated, e.g. a velocity from a measured position)."""
        observed = self.meta.get("observed")
        names = self.state_names
        if observed is None:
            return list(range(self.state_dim))
        unknown = [o for o in observed if o not in names]
        if unknown or not observed:
            raise DataError(
                f"{self.meta.get('source', 'trajectories')}: meta['observed'] = {list(observed)} must name at least "
                f"one of the states {names}" + (f"; unknown: {unknown}" if unknown else "") + "."
            )
        return [d for d, name in enumerate(names) if name in observed]

    @property
    def latent_index(self) -> list[int]:
        """Indices of the state columns that are not measured (estimated; see `observed_index`)."""
        observed = set(self.observed_index)
        return [d for d in range(self.state_dim) if d not in observed]

    def measured_states(self) -> dict[str, Any]:
        """What a report says about unmeasured states: {} when every state is measured, else ``observed`` (the
        measured state names: errors and losses are on these) and ``estimated`` ({latent state: how it was
        estimated}, from ``meta["estimated"]``)."""
        latent = self.latent_index
        if not latent:
            return {}
        names, how = self.state_names, self.meta.get("estimated") or {}
        return {
            "observed": [names[d] for d in self.observed_index],
            "estimated": {names[d]: str(how.get(names[d], "no estimate recorded")) for d in latent},
        }

    @property
    def control_names(self) -> list[str]:
        names = self.meta.get("control_names")
        return list(names) if names else [f"u{i}" for i in range(self.control_dim)]

    @property
    def system_name(self) -> str:
        return str(self.meta.get("system", "data"))

    # ---- checks --------------------------------------------------------------------------------------
    def validate(self, source: str = "trajectories") -> None:
        """Raise `DataError` naming what is wrong with the arrays (shapes, finiteness, time grid, graph)."""
        t, x = self.t, self.x
        if t.dim() != 1:
            raise DataError(f"{source}: `t` must be 1-D [T]; got shape {tuple(t.shape)}.")
        if x.dim() != 4:
            raise DataError(
                f"{source}: `x` must be [B, T, N, D] (trajectories, times, nodes, states); got shape "
                f"{tuple(x.shape)}. A single trajectory needs a leading axis of size 1."
            )
        if x.shape[1] != t.shape[0]:
            raise DataError(f"{source}: `x` has {x.shape[1]} time points but `t` has {t.shape[0]}.")
        if t.shape[0] < 2:
            raise DataError(f"{source}: need at least 2 time points; got {t.shape[0]}.")
        if not torch.isfinite(t).all():
            k = int(torch.nonzero(~torch.isfinite(t))[0])
            raise DataError(
                f"{source}: `t` holds {float(t[k])} at index {k} (time points must be finite numbers). Remove or "
                "interpolate that sample."
            )
        steps = t[1:] - t[:-1]
        if (steps <= 0).any():
            k = int(torch.nonzero(steps <= 0)[0])
            raise DataError(
                f"{source}: time points must be strictly increasing; t[{k}]={float(t[k]):g} is followed by "
                f"t[{k + 1}]={float(t[k + 1]):g}. Sort each trajectory by time and drop duplicates."
            )
        _check_finite(x, "x", source)
        if self.u is not None:
            if self.u.dim() != 4 or self.u.shape[:3] != x.shape[:3]:
                raise DataError(
                    f"{source}: `u` must be [B, T, N, C] matching x's [B, T, N] = {tuple(x.shape[:3])}; "
                    f"got {tuple(self.u.shape)}."
                )
            _check_finite(self.u, "u", source)
        ei = self.edge_index
        if ei.dtype not in (torch.int64, torch.int32):
            raise DataError(f"{source}: `edge_index` must be integer; got {ei.dtype}.")
        if ei.dim() == 2:
            if ei.shape[0] != 2:
                raise DataError(f"{source}: `edge_index` must be [2, E] (sender, receiver); got {tuple(ei.shape)}.")
        elif ei.dim() == 3:
            if ei.shape[0] != x.shape[0] or ei.shape[1] != 2:
                raise DataError(
                    f"{source}: per-trajectory `edge_index` must be [B, 2, E] with B={x.shape[0]}; "
                    f"got {tuple(ei.shape)}."
                )
        else:
            raise DataError(f"{source}: `edge_index` must be [2, E] or [B, 2, E]; got {tuple(ei.shape)}.")
        valid = ei[ei >= 0] if ei.dim() == 3 else ei
        if ei.dim() == 2 and (ei < 0).any():
            raise DataError(f"{source}: `edge_index` has negative node ids; node ids run from 0 to N-1.")
        if valid.numel() and int(valid.max()) >= x.shape[2]:
            raise DataError(
                f"{source}: `edge_index` names node {int(valid.max())} but the data has only "
                f"{x.shape[2]} nodes (ids 0..{x.shape[2] - 1})."
            )
        if self.node_features is not None and self.node_features.dim() not in (2, 3):
            raise DataError(f"{source}: `node_features` must be [N, F] or [B, N, F].")
        names = self.meta.get("state_names")
        if names is not None and len(names) != x.shape[3]:
            raise DataError(f"{source}: meta has {len(names)} state names but x has {x.shape[3]} state columns.")

    # ---- views ---------------------------------------------------------------------------------------
    def subset(self, index: torch.Tensor | slice | list[int]) -> Trajectories:
        """The trajectories selected by `index` (along B), sharing meta."""
        if isinstance(index, list):
            index = torch.as_tensor(index, dtype=torch.long)
        return replace(
            self,
            x=self.x[index],
            u=None if self.u is None else self.u[index],
            edge_index=self.edge_index if self.shared_graph else self.edge_index[index],
            node_features=(
                self.node_features
                if self.node_features is None or self.node_features.dim() == 2
                else self.node_features[index]
            ),
        )

    def time_slice(self, start: int, stop: int) -> Trajectories:
        """The time points start..stop−1 of every trajectory (a window of the records)."""
        return replace(
            self, t=self.t[start:stop], x=self.x[:, start:stop], u=None if self.u is None else self.u[:, start:stop]
        )

    def inputs(self, start: int = 0, stop: int | None = None) -> Inputs:
        """What a rollout over the time points start..stop−1 reads beside the states: `u` over those times; the
        graph, node features and meta (the same dict) as they are."""
        return Inputs(
            edge_index=self.edge_index,
            u=None if self.u is None else self.u[:, start:stop],
            node_features=self.node_features,
            meta=self.meta,
        )

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Trajectories:
        """Move every tensor, time `t` included, to `device`, and cast the floating ones (`t`, `x`, `u`,
        `node_features`) to `dtype`; the integer `edge_index` keeps its dtype, and `dtype=None` casts nothing."""
        return replace(
            self,
            t=_cast(self.t, device, dtype),
            x=_cast(self.x, device, dtype),
            u=_cast(self.u, device, dtype),
            edge_index=self.edge_index.to(device),
            node_features=_cast(self.node_features, device, dtype),
        )

    @staticmethod
    def concat(parts: list[Trajectories]) -> Trajectories:
        """Stack trajectories that share a time grid and node count along B."""
        first = parts[0]
        for p in parts[1:]:
            if p.t.shape != first.t.shape or not torch.allclose(p.t, first.t):
                raise DataError("cannot concatenate trajectories on different time grids.")
        shared = all(p.shared_graph for p in parts) and all(
            p.edge_index.shape == first.edge_index.shape and torch.equal(p.edge_index, first.edge_index) for p in parts
        )
        if shared:
            edge_index = first.edge_index
        else:
            per = [p.edge_index.expand(len(p), -1, -1) if p.shared_graph else p.edge_index for p in parts]
            e_max = max(e.shape[2] for e in per)
            edge_index = torch.cat([torch.nn.functional.pad(e, (0, e_max - e.shape[2]), value=-1) for e in per], dim=0)
        controls = [p.u for p in parts if p.u is not None]
        if first.u is not None and len(controls) != len(parts):
            raise DataError("cannot concatenate trajectories with controls `u` and trajectories without.")
        return Trajectories(
            t=first.t,
            x=torch.cat([p.x for p in parts]),
            edge_index=edge_index,
            u=None if first.u is None else torch.cat(controls),
            node_features=first.node_features,
            meta=dict(first.meta),
        )


@overload
def _cast(a: torch.Tensor, device: torch.device | str | None, dtype: torch.dtype | None) -> torch.Tensor: ...
@overload
def _cast(a: None, device: torch.device | str | None, dtype: torch.dtype | None) -> None: ...
def _cast(a: torch.Tensor | None, device: torch.device | str | None, dtype: torch.dtype | None) -> torch.Tensor | None:
    """`a` on `device`, cast to `dtype` if it is floating (integer tensors keep their dtype)."""
    if a is None:
        return None
    return a.to(device=device, dtype=dtype if a.is_floating_point() and dtype else a.dtype)


def _check_finite(a: torch.Tensor, name: str, source: str) -> None:
    bad = ~torch.isfinite(a)
    if bad.any():
        b, ti, n, d = (int(v) for v in torch.nonzero(bad)[0])
        raise DataError(
            f"{source}: `{name}` has NaN/inf (first at trajectory {b}, time index {ti}, node {n}, "
            f"column {d}; {int(bad.sum())} values in all). Remove or interpolate those samples."
        )


def grid_step(t: torch.Tensor) -> float:  # t: [T] time points
    """The step of a uniform time grid (NaN if the grid is not uniform)."""
    if t.numel() < 2:
        return float("nan")
    steps = (t[1:] - t[:-1]).double()
    spread = float(steps.max() - steps.min())
    return float(steps.mean()) if spread <= 1e-6 * float(steps.abs().max()) else float("nan")
