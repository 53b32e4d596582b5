"""What every N-body model shares: data conventions, graph building, the rollout loop, one-step training and
the paper's energy metric.

Data conventions (`mpsim.systems.nbody`): node state (x, y, vx, vy); node features [B, N, 2] (mass, charge);
the periodic box side L comes from the data's ``meta["box_size"]`` at run time, never from the model config,
so a model trained at one N runs at any other (spec §7.6).

Rollouts rebuild the graph from the model's own prediction before every step (spec §5). A trajectory
whose prediction turns NaN/inf is marked diverged: its remaining states are NaN (the metrics count it in
``n_diverged``) and, so that graph building stays well defined, it continues from its initial state
internally.

Training is one-step (spec §4): each trajectory of a batch contributes `pairs_per_trajectory` random
(state_t, state_{t+1}) pairs, and the loss is the MSE over particles and (x, y, vx, vy) with the position
error taken by minimum image. The trainer's `trainer.loss` (Huber for MP-NODE) does not apply.

Energy (`EnergyLog`): the paper's relative energy error |H(x̂_k) - H(x_0)| / |H(x_0)| at fixed steps k,
computed with the generating system's own Hamiltonian (softened minimum-image pair potential, from
``meta["params"]``), next to the data's own drift at the same k (``meta["energy_drift_mean"]``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import torch

from mpsim.errors import ConfigError, IncompatibleError
from mpsim.graphs.hierarchy import build_hierarchy, hierarchy_depth
from mpsim.graphs.knn import full_graph, knn_graph
from mpsim.graphs.order import spatial_order
from mpsim.metrics import select_features
from mpsim.models.base import Model
from mpsim.models.gn_blocks import ParticleEdges, take_rows
from mpsim.periodic import state_difference, wrap_positions

if TYPE_CHECKING:
    from collections.abc import Callable

    from mpsim.data.trajectories import Inputs, Trajectories

GRAPHS = ("full", "knn", "hierarchical")


def box_size_of(meta: dict[str, Any] | None) -> float:
    """The periodic box side L recorded by the data (`NBody.simulate` writes ``meta["box_size"]``)."""
    box = (meta or {}).get("box_size")
    if box is None:
        box = (meta or {}).get("params", {}).get("box_size")
    if box is None:
        raise IncompatibleError(
            "N-body models need the periodic box size of the data: meta['box_size'] is missing. Use "
            'system=nbody* data, or add "box_size": L to the meta JSON of your .npz file.'
        )
    return float(box)


def particle_features(
    node_features: torch.Tensor | None,  # [B, N, F] or [N, F] (mass, charge); None: unit masses
    b: int,
    n: int,
    like: torch.Tensor,  # tensor giving dtype and device
) -> torch.Tensor:
    """[B, N, 2] (mass, charge) for every sample."""
    if node_features is None:
        ones = torch.ones(b, n, 1, dtype=like.dtype, device=like.device)
        return torch.cat([ones, torch.zeros_like(ones)], dim=-1)
    nf = node_features.to(dtype=like.dtype, device=like.device)
    nf = nf.expand(b, n, nf.shape[-1]) if nf.dim() == 2 or nf.shape[0] == 1 else nf
    if nf.shape[-1] == 1:  # masses only: no charges
        nf = torch.cat([nf, torch.zeros_like(nf)], dim=-1)
    return nf[..., :2]


class ParticleModel(Model):
    """Base class of the N-body models: `step` advances [B, N, 4] states by one time step.

    Args:
        state_dim: 4 (x, y, vx, vy); other data is refused by `check_compatible`.
        control_dim: 0.
        graph: ``full`` (all pairs, O(N²)), ``knn`` (periodic k nearest neighbours) or ``hierarchical``
            (the quadtree of Martinkus et al.; O(N)).
        k: neighbours per particle for ``graph=knn`` (paper: 15).
        depth: quadtree depth for ``graph=hierarchical``; None: round(log4 N) of the data at run time.
        charge: use the particle charge as a feature (Coulomb data); the model refuses charged data
            without it.
        pairs_per_trajectory: random (t, t+1) pairs each training trajectory contributes per batch
            (trainer.batch_size trajectories × this = the paper's batch of states; reference: 100).
        energy_horizons: steps at which the paper's energy error is reported.
        energy_flag: a trajectory counts as ill-conditioned for the relative energy error when
            |H0| < energy_flag · (KE0 + |PE0|) (Coulomb at N = 100 has |H0| near 0 for a few %; spec §1).
        solver: unused (the models integrate themselves); accepted from the command layer.
    """

    def __init__(
        self,
        state_dim: int = 4,
        control_dim: int = 0,
        graph: str = "hierarchical",
        k: int = 15,
        depth: int | None = None,
        charge: bool = False,
        pairs_per_trajectory: int = 8,
        energy_horizons: Sequence[int] = (20, 200),
        energy_flag: float = 0.1,
        solver: Any = None,
    ) -> None:
        super().__init__(state_dim, control_dim)
        if graph not in GRAPHS:
            raise ConfigError(f"model.graph={graph!r} is unknown; choose one of {', '.join(GRAPHS)}.")
        if k < 1 or pairs_per_trajectory < 1 or (depth is not None and depth < 2):
            raise ConfigError(
                f"need model.k >= 1, model.pairs_per_trajectory >= 1 and model.depth >= 2 (or null); got "
                f"{k}, {pairs_per_trajectory}, {depth}."
            )
        self.graph, self.k, self.depth, self.charge = graph, int(k), depth, bool(charge)
        self.pairs_per_trajectory = int(pairs_per_trajectory)
        self.n_feat = 4 if self.charge else 3  # non-position particle features: m, (q), 2 velocity/momentum
        self.energy = EnergyLog(energy_horizons, energy_flag)
        # training pairs are drawn from a counter saved with the weights, so `resume` redraws the same pairs
        self.register_buffer("pair_draws", torch.zeros((), dtype=torch.long))
        self.register_buffer("trained_dt", torch.zeros(()))  # step of the training data (0: not trained yet)
        self._full_cache: dict[tuple, torch.Tensor] = {}
        self._edge_counts: list[float] = []

    # ---- to implement ----------------------------------------------------------------------------------
    def advance_in_graph_order(
        self,
        x: torch.Tensor,  # [B, N, 4] states, particles in graph order (`graph.order`)
        nf: torch.Tensor,  # [B, N, 2] (mass, charge), in graph order
        graph: ParticleEdges,  # the graph of `x`
        box: float,
        dt: float,
    ) -> torch.Tensor:
        """[B, N, 4] the state one step of `dt` later, in graph order (positions wrapped into the box)."""
        raise NotImplementedError

    def advance(
        self,
        x: torch.Tensor,  # [B, N, 4] states, in the caller's particle order
        nf: torch.Tensor,  # [B, N, 2] (mass, charge)
        graph: ParticleEdges,  # the graph of `x` (from `build_graph`)
        box: float,
        dt: float,
    ) -> torch.Tensor:
        """[B, N, 4] the state one step of `dt` later, in the caller's particle order.

        Renumbers the particles into the graph's order, runs `advance_in_graph_order`, and puts the prediction
        back: the same result (up to float rounding) as on a graph built without reordering.
        """
        out = self.advance_in_graph_order(graph.to_graph_order(x), graph.to_graph_order(nf), graph, box, dt)
        return graph.to_caller_order(out)

    def step(
        self,
        x: torch.Tensor,  # [B, N, 4] states
        nf: torch.Tensor,  # [B, N, 2] (mass, charge)
        box: float,
        dt: float,
    ) -> torch.Tensor:
        """[B, N, 4] one step: build the graph of `x`, then `advance`."""
        return self.advance(x, nf, self.build_graph(x[..., :2], nf, x[..., 2:], box), box, dt)

    def dt_step_fixed(self) -> bool:
        """Whether the model only knows the training step (DeltaGN) rather than integrating an ODE (HOGN)."""
        return True

    # ---- graphs ----------------------------------------------------------------------------------------
    # Renumber particles along the Z-order curve before building kNN and hierarchical graphs (memory locality
    # of the forward pass's gathers and segment sums; see `graphs.order`). False: keep the caller's order.
    reorder_particles: bool = True

    # buffers (nn.Module.__getattr__ would type them as Tensor | Module)
    pair_draws: torch.Tensor
    trained_dt: torch.Tensor

    def build_graph(
        self,
        pos: torch.Tensor,  # [B, N, 2] positions
        nf: torch.Tensor,  # [B, N, 2] (mass, charge)
        vel: torch.Tensor,  # [B, N, 2] velocities (cell features)
        box: float,
    ) -> ParticleEdges:
        """The particle edges (and for ``hierarchical`` the quadtree with its cell features) of a state.

        For ``knn`` and ``hierarchical`` the particles are first renumbered along the Z-order curve of the
        quadtree's lowest grid (`graphs.order.spatial_order`), so that the edges, sorted by receiver, have
        senders close by in memory and each cell's particles are contiguous; the graph records that order
        (`ParticleEdges.order`) and `advance` returns predictions in the caller's order. The all-pairs graph
        keeps the caller's order (every sender is gathered for every receiver anyway).
        """
        b, n, _ = pos.shape
        order = None
        if self.reorder_particles and self.graph != "full" and n > 2:
            depth = self.depth if self.graph == "hierarchical" and self.depth is not None else hierarchy_depth(n)
            order = spatial_order(pos, box, depth)  # [B*N]
            pos, nf, vel = (take_rows(v, order) for v in (pos, nf, vel))
        if self.graph == "full":
            key = (b, n, pos.device)
            if key not in self._full_cache:  # the all-pairs topology never changes: build it once
                self._full_cache = {key: full_graph(pos.detach()[:, :2].new_zeros(b, n, 2), box).edge_index}
            edges = ParticleEdges(self._full_cache[key], b, n)
        elif self.graph == "knn":
            edges = ParticleEdges(knn_graph(pos.detach(), box, self.k).edge_index, b, n, order=order)
        else:
            charge = nf[..., 1] if self.charge else None
            h = build_hierarchy(pos.detach(), box, mass=nf[..., 0], vel=vel.detach(), charge=charge, depth=self.depth)
            edges = ParticleEdges(h.pp_edge_index, b, n, h, order)
        if not torch.is_grad_enabled() and len(self._edge_counts) < 10_000:
            extra = 1 if edges.hierarchy is not None else 0  # the cell -> particle edge
            self._edge_counts.append(edges.edge_index.shape[1] / max(1, b * n) + extra)
        return edges

    # ---- checks ----------------------------------------------------------------------------------------
    def check_compatible(
        self, state_dim: int, control_dim: int, n_nodes: int, trained_nodes: int | None = None
    ) -> None:
        """Particles only: state (x, y, vx, vy), no controls; any number of particles."""
        check_particle_data(type(self).__name__, state_dim, control_dim)

    def _check_charges(self, nf: torch.Tensor) -> None:  # nf: [B, N, 2]
        if not self.charge and bool((nf[..., 1] != 0).any()):
            raise IncompatibleError(
                f"the data has particle charges (Coulomb) but this {type(self).__name__} was built without the "
                "charge feature. Train with model.charge=true (or use an experiment=nbody*_coulomb* config)."
            )

    def _check_dt(self, dt: float) -> None:
        trained = float(self.trained_dt)
        if self.dt_step_fixed() and trained > 0 and abs(dt - trained) > 1e-4 * trained:
            raise IncompatibleError(
                f"{type(self).__name__} predicts one step of the training data's dt = {trained:.6g}; this data "
                f"has dt = {dt:.6g}. Evaluate on data with data.dt={trained:.6g} (HOGN integrates any dt)."
            )

    # ---- rollout ---------------------------------------------------------------------------------------
    def rollout(
        self,
        x0: torch.Tensor,  # [B, N, 4] initial states (raw units)
        t: torch.Tensor,  # [T] times
        inputs: Inputs,  # node features [B, N, 2] or [N, 2] (mass, charge), meta: box_size, params (energy)
    ) -> torch.Tensor:
        """[B, T, N, 4] free rollout from x0; the graph is rebuilt from the prediction before every step (the
        graph of `inputs` is not read; there are no controls)."""
        record = not torch.is_grad_enabled()  # an evaluation (no_grad), not a training rollout
        meta = inputs.meta
        box = box_size_of(meta)
        b, n, _ = x0.shape
        nf = particle_features(inputs.node_features, b, n, x0)
        self._check_charges(nf)
        steps = (t[1:] - t[:-1]).tolist()
        for dt in set(round(s, 12) for s in steps):
            self._check_dt(dt)
        self._edge_counts = []
        x = x0
        out = [x0]
        dead = torch.zeros(b, dtype=torch.bool, device=x0.device)
        nan = torch.full_like(x0, math.nan)
        for dt in steps:
            x_new = self.step(x, nf, box, dt).detach()
            dead = dead | ~torch.isfinite(x_new).flatten(1).all(dim=1)
            d = dead[:, None, None]
            out.append(torch.where(d, nan, x_new))
            x = torch.where(d, x0, x_new)  # a diverged sample restarts from x0 internally: graphs stay finite
        pred = torch.stack(out, dim=1)
        if record:
            self.energy.record(pred, nf, meta)
        return pred

    # ---- training --------------------------------------------------------------------------------------
    def training_loss(
        self,
        batch: Trajectories,
        t: torch.Tensor,  # [T] times in the model's dtype
        loss_fn: Callable[..., torch.Tensor] | None = None,  # unused: one-step MSE with minimum-image positions
        delta: float = 1.0,  # unused
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(one-step MSE, [B, P, N, 4] predicted next states) on P random pairs per trajectory."""
        x = batch.x  # [B, T, N, 4]
        b, n_t, n, _ = x.shape
        box = box_size_of(batch.meta)
        dt = float(t[1] - t[0])
        if self.dt_step_fixed() and float(self.trained_dt) > 0:
            self._check_dt(dt)
        self.trained_dt.fill_(dt)
        gen = torch.Generator().manual_seed(1_000_003 + int(self.pair_draws))
        self.pair_draws += 1
        p = self.pairs_per_trajectory
        when = torch.randint(0, n_t - 1, (b, p), generator=gen).to(x.device)  # [B, P] time index of each pair
        rows = torch.arange(b, device=x.device)[:, None]
        x_in, x_out = x[rows, when], x[rows, when + 1]  # [B, P, N, 4]
        nf = particle_features(batch.node_features, b, n, x)
        self._check_charges(nf)
        nf = nf[:, None].expand(b, p, n, 2).reshape(b * p, n, 2)
        self.before_training_step(x_in, x_out, box)
        pred = self.step(x_in.reshape(b * p, n, 4), nf, box, dt).reshape(b, p, n, 4)
        err = state_difference(pred, x_out, [box, box, None, None])  # positions by minimum image
        return select_features(err, batch.observed_index).pow(2).mean(), pred

    def before_training_step(
        self,
        x_in: torch.Tensor,  # [B, P, N, 4] input states
        x_out: torch.Tensor,  # [B, P, N, 4] target states
        box: float,
    ) -> None:
        """Hook before each training step (DeltaGN fits its output scale here once)."""

    # ---- reports ---------------------------------------------------------------------------------------
    def report(self) -> dict[str, Any]:
        out = {"graph": self.graph, **self.energy.summary()}
        if self._edge_counts:
            out["edges_per_particle"] = sum(self._edge_counts) / len(self._edge_counts)
        return {"nbody": out}

    def report_lines(self) -> list[tuple[str, str]]:
        rows = self.energy.lines()
        if self._edge_counts:
            rows.append(
                (
                    "graph",
                    f"{self.graph}, {sum(self._edge_counts) / len(self._edge_counts):.1f} "
                    "incoming particle edges per particle (mean over the last rollout)",
                )
            )
        return rows


def check_particle_data(name: str, state_dim: int, control_dim: int) -> None:
    """Raise `IncompatibleError` unless the data is N-body data: state (x, y, vx, vy), no controls."""
    if state_dim != 4 or control_dim != 0:
        raise IncompatibleError(
            f"{name} simulates particles with state (x, y, vx, vy) and no controls; the data has {state_dim} "
            f"states and {control_dim} controls per node. Use system=nbody* (or N-body data with 4 state columns)."
        )


class EnergyLog:
    """The paper's energy error of the latest evaluation pass over a data split.

    `record` is called by every evaluation rollout. The trainer rolls out the validation and test splits each
    epoch and `evaluate_model` the test split last, in batches of up to 512 trajectories; rollouts of the same
    split (same ``meta`` object) are merged until that split's first batch comes round again, which starts a
    new pass. `summary` reports the most recent pass — after `mpsim train`/`mpsim eval`, the test split.

    Args:
        horizons: steps k at which |H(x̂_k) - H(x_0)| / |H(x_0)| is reported.
        flag: |H0| < flag · (KE0 + |PE0|) marks a trajectory as ill-conditioned for the relative error.
    """

    def __init__(self, horizons: Sequence[int], flag: float) -> None:
        self.horizons, self.flag = [int(h) for h in horizons], float(flag)
        self._passes: dict[int, dict[str, Any]] = {}
        self._last: int | None = None

    def record(
        self,
        pred: torch.Tensor,  # [B, T, N, 4] rollout (pred[:, 0] is the true initial state)
        nf: torch.Tensor,  # [B, N, 2] (mass, charge)
        meta: dict[str, Any] | None,
    ) -> None:
        system = _system_from_meta(meta, pred.shape[2])
        if system is None:
            return
        x = pred.detach().to(torch.float64)
        f = nf.detach().to(torch.float64)
        kinetic0 = 0.5 * (f[..., 0] * x[:, 0, :, 2:].pow(2).sum(-1)).sum(-1)  # [B]
        potential0 = system.potential_energy(x[:, 0, :, :2], f)  # [B]
        h0 = kinetic0 + potential0
        ill = h0.abs() < self.flag * (kinetic0.abs() + potential0.abs())
        rel = {}
        for h in self.horizons:
            k = min(h, x.shape[1] - 1)
            hk = system.energy(x[:, k], f)
            rel[k] = ((hk - h0).abs() / h0.abs().clamp(min=1e-300)).tolist()  # NaN for diverged runs
        key = id(meta)
        first = float(x[:, 0].sum())
        entry = self._passes.get(key)
        if entry is None or entry["first"] == first:
            if len(self._passes) > 16:
                self._passes.clear()
            entry = {"first": first, "rel": {k: [] for k in rel}, "ill": [], "h0": [], "meta": meta}
            self._passes[key] = entry
        for k, v in rel.items():
            entry["rel"][k] += v
        entry["ill"] += ill.tolist()
        entry["h0"] += h0.tolist()
        self._last = key

    def summary(self) -> dict[str, Any]:
        """{"energy_error": {k: mean}, "data_energy_drift": {k: mean}, "n_ill_conditioned", ...} (empty if none)."""
        if self._last is None:
            return {}
        entry = self._passes[self._last]
        drift = (entry["meta"] or {}).get("energy_drift_mean")
        out: dict[str, Any] = {
            "energy_trajectories": len(entry["h0"]),
            "energy_error": {},
            "data_energy_drift": {},
            "n_ill_conditioned": int(sum(entry["ill"])),
            "energy_error_well_conditioned": {},
        }
        for k, values in entry["rel"].items():
            finite = [v for v in values if math.isfinite(v)]
            good = [v for v, bad in zip(values, entry["ill"], strict=True) if not bad and math.isfinite(v)]
            out["energy_error"][str(k)] = sum(finite) / len(finite) if finite else math.nan
            out["energy_error_well_conditioned"][str(k)] = sum(good) / len(good) if good else math.nan
            out["data_energy_drift"][str(k)] = float(drift[k]) if drift is not None and k < len(drift) else math.nan
        out["min_abs_h0"] = min(abs(v) for v in entry["h0"])
        return out

    def lines(self) -> list[tuple[str, str]]:
        s = self.summary()
        if not s:
            return []
        cells = ", ".join(
            f"{k} steps {v:.3g} (data {s['data_energy_drift'][k]:.2g})" for k, v in s["energy_error"].items()
        )
        rows = [("energy error |ΔH/H0|", cells)]
        if s["n_ill_conditioned"]:
            good = ", ".join(f"{k}: {v:.3g}" for k, v in s["energy_error_well_conditioned"].items())
            rows.append(
                (
                    "  ill-conditioned H0",
                    f"{s['n_ill_conditioned']} of {s['energy_trajectories']} "
                    f"trajectories have |H0| < {self.flag:g}·(KE+|PE|) (min |H0| "
                    f"{s['min_abs_h0']:.3g}); without them {good}",
                )
            )
        return rows


def _system_from_meta(meta: dict[str, Any] | None, n: int) -> Any:
    """The generating `NBody` (for its Hamiltonian) from the data's metadata, or None without one."""
    from mpsim.systems.nbody import NBody

    params = (meta or {}).get("params") or {}
    if "force" not in params:
        return None
    return NBody(
        n_particles=n,
        force=params["force"],
        box_size=box_size_of(meta),
        softening=float(params.get("softening", 0.2)),
        G=float(params.get("G", 2.0)),
    )


def wrap_state(x: torch.Tensor, box: float) -> torch.Tensor:  # x: [..., 4] states
    """[..., 4] states with positions mapped into the box [-L/2, L/2)."""
    return torch.cat([wrap_positions(x[..., :2], box), x[..., 2:]], dim=-1)
