"""Gravitational or Coulomb N-body in a 2-D periodic box (the data of Martinkus et al., AAAI 2021).

N particles live in the box [-L/2, L/2)^2 with L = sqrt(12 N) (one particle per 12 square units). With a
Plummer softening ε, a_i = c (s_i / m_i) Σ_j s_j (x_j - x_i) / (r_ij² + ε²)^{3/2}, where

- gravity: s = m, c = +G, so φ_ij = -G m_i m_j / sqrt(r² + ε²) (attractive);
- Coulomb: s = q, c = -k, so φ_ij = +k q_i q_j / sqrt(r² + ε²) (like charges repel).

Separations use the minimum image (only the nearest copy of each particle counts; no lattice sum), as in
the reference data. The energy convention follows the same rule, so it is exactly the Hamiltonian whose
gradient is the simulated force:

    H = Σ_i ½ m_i |v_i|² + Σ_{i<j} φ(r_ij),   r_ij the minimum-image distance, no self-energy, no Ewald sum.

The minimum-image potential is continuous; its force has a kink where a separation component crosses L/2
(the force there is O(G / L²), tiny).

Integrator. The reference uses a velocity-Verlet leapfrog with individual power-of-two time steps
(η = 0.001) that is not exactly symplectic: about 110 force evaluations per particle per base step and a
relative energy drift of 3e-5 to 1.2e-4 after 200 base steps at N = 20 and 100 (spec §1). Here every
particle takes the same fine step dt / `substeps` of the same velocity Verlet, which is symplectic and
time-reversible, so the energy error oscillates within a bound instead of drifting. Measured at N = 100
(200 base steps, 6 trajectories):

- gravity, 8 substeps (8 force evaluations per base step): |ΔH/H0| at step 200 is 1e-7 .. 6e-6 and at most
  1.1e-5 over the run, against the reference's 3.4e-5 .. 8.5e-5 at ~110 evaluations;
- Coulomb, 32 substeps: |ΔH| at most 5e-4 over the run (8 substeps: 7e-3). Opposite charges form tight
  softened pairs (small-oscillation ω ≈ sqrt(2 k |q_i q_j| (1/m_i + 1/m_j) / ε³) ≈ 34), so Coulomb needs the
  finer default step; |H0| itself can be close to 0 there (spec §1), which makes its *relative* drift
  ill-conditioned: `meta["energy_initial"]` records H0 so such runs can be flagged.

`tests/systems/test_nbody.py` checks the gravity numbers against the reference's.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from typing import Any

import torch

from mpsim.data.trajectories import Trajectories
from mpsim.errors import ConfigError
from mpsim.periodic import minimum_image, wrap_positions
from mpsim.systems.base import System, check_fixed_steps

# Pairwise work is tiled so that one tile holds at most this many pairs. On a CPU a tile's temporaries
# (512 kB each) stay in cache, which measured 2-4x faster than 16 MB tiles at N = 1000; on a GPU large tiles
# keep the device busy. Either way all-pairs forces at N = 10 000 never need ~1 GB temporaries.
_PAIR_BUDGET = 1 << 16
_PAIR_BUDGET_CUDA = 1 << 26

FORCES = ("gravity", "coulomb")
# Fine steps per base step: Coulomb's bound opposite-charge pairs oscillate faster (module docstring).
DEFAULT_SUBSTEPS = {"gravity": 8, "coulomb": 32}


class NBody(System):
    """Gravitational or Coulomb N-body in a 2-D periodic box; node state (x, y, vx, vy).

    Static node features (`Trajectories.node_features`, [B, N, 2]) are (mass, charge); the charge column is
    zero for gravity.

    Args:
        name: dataset/checkpoint name.
        n_particles: N.
        force: ``"gravity"`` or ``"coulomb"``.
        box_size: side L of the periodic box; default sqrt(12 N).
        softening: Plummer softening length ε.
        G: coupling constant: G for gravity, k for Coulomb.
        dt: base step (the sampling step of generated data).
        n_steps: base steps per generated trajectory (T = n_steps + 1 stored states).
        substeps: velocity-Verlet steps per base step of `dt` (the fine step is dt / substeps; a different
            sampling step passed to `simulate` keeps the fine step at most this size). Default 8 for
            gravity, 32 for Coulomb (see the module docstring).
        mass: mass of every particle.
        velocity_range: uniform range of each initial velocity component.
        charge_range: uniform range of |q| (Coulomb); the sign is + or - with equal probability.
        effects: must be empty (extra terms would break the symplectic integrator).
    """

    state_names = ("x", "y", "vx", "vy")
    node_feature_names = ("mass", "charge")

    def __init__(
        self,
        name: str = "nbody100",
        n_particles: int = 100,
        force: str = "gravity",
        box_size: float | None = None,
        softening: float = 0.2,
        G: float = 2.0,
        dt: float = 0.01,
        n_steps: int = 200,
        substeps: int | None = None,
        mass: float = 1.0,
        velocity_range: Sequence[float] = (-1.0, 1.0),
        charge_range: Sequence[float] = (0.5, 1.5),
        effects: Sequence[Any] = (),
    ) -> None:
        if n_particles < 2:
            raise ConfigError(f"system.n_particles must be >= 2; got {n_particles}.")
        if force not in FORCES:
            raise ConfigError(f"system.force must be one of {', '.join(FORCES)}; got {force!r}.")
        if softening <= 0:
            raise ConfigError(f"system.softening must be > 0 (Plummer ε); got {softening}.")
        substeps = DEFAULT_SUBSTEPS.get(force, 1) if substeps is None else int(substeps)
        if dt <= 0 or n_steps < 1 or substeps < 1:
            raise ConfigError(f"need dt > 0, n_steps >= 1, substeps >= 1; got {dt}, {n_steps}, {substeps}.")
        if mass <= 0:
            raise ConfigError(f"system.mass must be > 0; got {mass}.")
        if effects:
            raise ConfigError(
                "system=nbody takes no effects: its symplectic integrator steps positions and velocities "
                "directly and never calls rhs(). Remove `system.effects`."
            )
        # the coupling is all-pairs and changes with the positions: graphs are built per state by the models
        super().__init__(name, n_particles, torch.zeros(2, 0, dtype=torch.long), effects)
        self.force = force
        self.box_size = float(math.sqrt(12 * n_particles) if box_size is None else box_size)
        self.softening = float(softening)
        self.G = float(G)
        self.dt = float(dt)
        self.horizon = int(n_steps)
        self.substeps = int(substeps)
        self.mass = float(mass)
        self.velocity_range = tuple(float(v) for v in velocity_range)
        self.charge_range = tuple(float(v) for v in charge_range)

    def params(self) -> dict[str, Any]:
        return {
            "n_particles": self.n_nodes,
            "force": self.force,
            "box_size": self.box_size,
            "softening": self.softening,
            "G": self.G,
            "dt": self.dt,
            "n_steps": self.horizon,
            "substeps": self.substeps,
            "mass": self.mass,
            "velocity_range": list(self.velocity_range),
            "charge_range": list(self.charge_range),
        }

    # ---- physics -------------------------------------------------------------------------------------
    def _strengths(
        self,
        node_features: torch.Tensor | None,  # [..., N, 2] (mass, charge) or None
        shape: torch.Size,  # leading shape [..., N] to broadcast to
        like: torch.Tensor,  # tensor giving dtype and device
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """([..., N] source strength s, [..., N] mass m): s = m for gravity, s = q for Coulomb."""
        if node_features is None:
            if self.force == "coulomb":
                raise ConfigError(
                    "Coulomb N-body needs the charges: pass node_features [B, N, 2] (mass, charge), e.g. "
                    "`traj.node_features` or `system.sample_node_features(n, generator)`."
                )
            m = torch.full(shape, self.mass, dtype=like.dtype, device=like.device)
            return m, m
        nf = node_features.to(dtype=like.dtype, device=like.device)
        while nf.dim() < len(shape) + 1:  # [B, N, F] against [B, T, N]: add the time axis after the batch
            nf = nf.unsqueeze(-3) if nf.dim() >= 3 else nf.unsqueeze(0)
        nf = nf.expand(*shape, nf.shape[-1])
        m = nf[..., 0]
        return (m if self.force == "gravity" else nf[..., 1]), m

    @property
    def _coef(self) -> float:
        """c in a_i = c (s_i/m_i) Σ_j s_j (x_j - x_i)/R³: +G pulls together, -k pushes like charges apart."""
        return self.G if self.force == "gravity" else -self.G

    def acceleration(
        self,
        pos: torch.Tensor,  # [B, N, 2] positions
        node_features: torch.Tensor | None = None,  # [B, N, 2] or [N, 2] (mass, charge); None: unit masses
    ) -> torch.Tensor:
        """[B, N, 2] softened minimum-image accelerations."""
        s, m = self._strengths(node_features, pos.shape[:-1], pos)
        return _pair_accelerations(pos, s, self._coef * s / m, self.box_size, self.softening**2)

    def dynamics(
        self,
        t: torch.Tensor,  # [] time (unused: autonomous)
        x: torch.Tensor,  # [B, N, 4] (x, y, vx, vy)
        u: torch.Tensor | None = None,  # unused: no controls
        node_features: torch.Tensor | None = None,  # [B, N, 2] (mass, charge); None: unit masses (gravity)
    ) -> torch.Tensor:
        """[B, N, 4] (v, a). For inspection only: `simulate` uses the symplectic integrator, not odeint."""
        return torch.cat([x[..., 2:], self.acceleration(x[..., :2], node_features)], dim=-1)

    def potential_energy(
        self,
        pos: torch.Tensor,  # [..., N, 2] positions
        node_features: torch.Tensor | None = None,  # [..., N, 2], [B, N, 2] or [N, 2] (mass, charge)
    ) -> torch.Tensor:
        """[...] Σ_{i<j} φ(r_ij) with minimum-image distances (see the module docstring)."""
        s, _ = self._strengths(node_features, pos.shape[:-1], pos)
        lead = pos.shape[:-2]
        n = pos.shape[-2]
        pot = _pair_potential(pos.reshape(-1, n, 2), s.reshape(-1, n), self.box_size, self.softening**2)
        return (-self._coef * pot).reshape(lead)

    def energy(
        self,
        x: torch.Tensor,  # [..., N, 4] states (x, y, vx, vy)
        node_features: torch.Tensor | None = None,  # [..., N, 2], [B, N, 2] for x [B, T, N, 4], or [N, 2]
    ) -> torch.Tensor:
        """[...] total energy H = kinetic + minimum-image softened pair potential (no Ewald sum).

        `node_features` (mass, charge) extends the base signature; None means unit masses and is only
        allowed for gravity.
        """
        s, m = self._strengths(node_features, x.shape[:-1], x)
        kinetic = 0.5 * (m * x[..., 2:].pow(2).sum(-1)).sum(-1)
        return kinetic + self.potential_energy(x[..., :2], node_features)

    # ---- sampling ------------------------------------------------------------------------------------
    def sample_initial_states(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """[n, N, 4] uniform positions in the box and uniform velocity components (net momentum kept)."""
        pos = (torch.rand(n, self.n_nodes, 2, generator=generator, dtype=torch.float64) - 0.5) * self.box_size
        lo, hi = self.velocity_range
        vel = lo + (hi - lo) * torch.rand(n, self.n_nodes, 2, generator=generator, dtype=torch.float64)
        return torch.cat([wrap_positions(pos, self.box_size), vel], dim=-1)

    def sample_node_features(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """[n, N, 2] (mass, charge): constant masses; charges ±U(charge_range) for Coulomb, 0 for gravity."""
        mass = torch.full((n, self.n_nodes), self.mass, dtype=torch.float64)
        if self.force == "gravity":
            return torch.stack([mass, torch.zeros_like(mass)], dim=-1)
        lo, hi = self.charge_range
        size = lo + (hi - lo) * torch.rand(n, self.n_nodes, generator=generator, dtype=torch.float64)
        sign = torch.where(torch.rand(n, self.n_nodes, generator=generator, dtype=torch.float64) < 0.5, -1.0, 1.0)
        return torch.stack([mass, sign * size], dim=-1)

    # ---- data ----------------------------------------------------------------------------------------
    def simulate(
        self,
        x0: torch.Tensor,  # [B, N, 4] initial states
        t: torch.Tensor,  # [T] output times (uniform grid)
        rtol: float | None = None,
        atol: float | None = None,
        method: str | None = None,
        *,
        node_features: torch.Tensor | None = None,  # [B, N, 2] or [N, 2] (mass, charge)
    ) -> Trajectories:
        """Integrate with velocity Verlet and store the states at `t`.

        Args:
            x0: [B, N, 4] initial (x, y, vx, vy); positions are wrapped into the box.
            t: [T] uniform output grid; each interval is split into ceil(Δt / (dt / substeps)) fine steps.
            rtol, atol, method: ignored (fixed-step symplectic integrator); kept for the `System` interface.
            node_features: [B, N, 2] (mass, charge); None means unit masses (gravity only).

        Returns:
            `Trajectories` with x [B, T, N, 4], node_features [B, N, 2], an empty `edge_index` (graphs are
            built per state), and in `meta` per trajectory: ``energy_initial`` (H0), ``energy_drift``
            (|H_T - H0| / |H0|), ``energy_drift_max`` (max over the stored states) — the floor for the
            energy metric; ``energy_drift_mean`` [T] (mean over trajectories at every step); ``box_size``
            and ``periods`` = [L, L, None, None] (positions are compared by minimum image).
        """
        x0 = x0.to(torch.float64)
        t = t.to(dtype=torch.float64, device=x0.device)
        if x0.dim() != 3 or x0.shape[1:] != (self.n_nodes, 4):
            raise ConfigError(f"x0 must be [B, {self.n_nodes}, 4] (x, y, vx, vy); got {tuple(x0.shape)}.")
        steps = t[1:] - t[:-1]
        if t.dim() != 1 or t.shape[0] < 2 or not torch.allclose(steps, steps[0], rtol=1e-9, atol=1e-12):
            raise ConfigError("NBody.simulate needs a uniform time grid t [T] with T >= 2.")
        base = float(steps[0])
        if base <= 0:
            raise ConfigError(f"time grid must increase; got step {base}.")
        n_sub = max(1, math.ceil(base / (self.dt / self.substeps) - 1e-9))
        check_fixed_steps(self.name, n_sub, base, self.dt)
        b = x0.shape[0]
        if node_features is None:
            s, m = self._strengths(None, x0.shape[:-1], x0)
            node_features = torch.stack([m, torch.zeros_like(m)], dim=-1)
        node_features = node_features.to(x0).expand(b, self.n_nodes, 2).contiguous()
        s, m = self._strengths(node_features, x0.shape[:-1], x0)
        scale = self._coef * s / m
        h, eps2, box = base / n_sub, self.softening**2, self.box_size

        out = torch.empty(b, t.shape[0], self.n_nodes, 4, dtype=torch.float64, device=x0.device)
        pos, vel = wrap_positions(x0[..., :2], box), x0[..., 2:].clone()
        acc = _pair_accelerations(pos, s, scale, box, eps2)
        out[:, 0] = torch.cat([pos, vel], dim=-1)
        for k in range(1, t.shape[0]):  # loop over time only; every step is vectorised over B and N
            for _ in range(n_sub):
                # velocity Verlet (kick-drift-kick): symplectic, one new force evaluation per fine step
                pos = wrap_positions(pos + h * vel + (0.5 * h * h) * acc, box)
                acc_new = _pair_accelerations(pos, s, scale, box, eps2)
                vel = vel + (0.5 * h) * (acc + acc_new)
                acc = acc_new
            out[:, k] = torch.cat([pos, vel], dim=-1)

        energy = self.energy(out, node_features)  # [B, T]
        rel = ((energy - energy[:, :1]) / energy[:, :1].abs()).abs()
        meta = self.meta(base)
        meta.update(
            node_feature_names=list(self.node_feature_names),
            box_size=box,
            integrator=f"velocity Verlet, uniform fine step dt/{n_sub}",
            force_evaluations_per_step=n_sub,
            energy_convention="kinetic + sum_{i<j} softened minimum-image pair potential (no Ewald sum)",
            energy_initial=energy[:, 0].tolist(),
            energy_drift=rel[:, -1].tolist(),
            energy_drift_max=rel.max(dim=1).values.tolist(),
            # mean over trajectories of |H_k - H0| / |H0| at every stored step k: the floor of the paper's
            # energy error at any horizon
            energy_drift_mean=rel.mean(dim=0).tolist(),
            # positions live on a torus of side L: metrics compare them by minimum image
            periods=[box, box, None, None],
        )
        return Trajectories(t=t, x=out, edge_index=self.edge_index, node_features=node_features, meta=meta)

    def generate(
        self,
        n: int,
        seed: int,
        dt: float | None = None,
        horizon: int | None = None,
        rtol: float | None = None,
        atol: float | None = None,
        burn_in: int = 0,
        device: torch.device | str | None = None,
    ) -> Trajectories:
        """`n` trajectories of `horizon` steps of `dt` from initial states and charges drawn with `seed`.

        The draws happen on the CPU (so a seed gives the same data on every device); the integration runs
        on `device` (default CPU). `rtol`/`atol` are ignored (fixed-step integrator); `burn_in` must be 0.
        """
        if burn_in:
            raise ConfigError(f"{self.name}: N-body data has no burn-in; got burn_in={burn_in}. Set data.burn_in=0.")
        dt = self.dt if dt is None else dt
        horizon = self.horizon if horizon is None else horizon
        if dt <= 0 or horizon < 1 or n < 1:
            raise ConfigError(f"need dt > 0, horizon >= 1 and n >= 1; got dt={dt}, horizon={horizon}, n={n}.")
        generator = torch.Generator().manual_seed(int(seed))
        x0 = self.sample_initial_states(n, generator)
        node_features = self.sample_node_features(n, generator)
        t = torch.arange(horizon + 1, dtype=torch.float64) * dt
        traj = self.simulate(x0.to(device), t.to(device), node_features=node_features.to(device))
        traj.meta["seed"] = int(seed)
        return traj


def _tiles(m: int, n: int, device: torch.device) -> Iterator[tuple[int, int, int, int]]:
    """(state0, state1, row0, row1) tiles of an [M, N, N] pair array within the pair budget.

    The loops run over memory tiles (a few for N = 100), never over single particles.
    """
    budget = _PAIR_BUDGET_CUDA if device.type == "cuda" else _PAIR_BUDGET
    states = max(1, budget // (n * n))
    rows = n if states > 1 else max(1, budget // n)
    for s0 in range(0, m, states):
        for r0 in range(0, n, rows):
            yield s0, min(m, s0 + states), r0, min(n, r0 + rows)


def _separations(
    pos: torch.Tensor,  # [M, N, 2] positions
    s0: int,
    s1: int,
    r0: int,
    r1: int,
    box: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """([m, r, N], [m, r, N]) minimum-image x_j - x_i, y_j - y_i for receivers i in [r0, r1)."""
    px, py = pos[s0:s1, :, 0], pos[s0:s1, :, 1]
    dx = px[:, None, :] - px[:, r0:r1, None]
    dy = py[:, None, :] - py[:, r0:r1, None]
    return minimum_image(dx, box), minimum_image(dy, box)  # odd-symmetric: pair forces stay antisymmetric


def _pair_accelerations(
    pos: torch.Tensor,  # [B, N, 2] positions
    source: torch.Tensor,  # [B, N] source strength s_j (mass or charge)
    scale: torch.Tensor,  # [B, N] c s_i / m_i
    box: float,
    eps2: float,
) -> torch.Tensor:
    """[B, N, 2] a_i = scale_i Σ_j s_j (x_j - x_i) / (r² + ε²)^{3/2} (the j = i term is 0·finite = 0)."""
    b, n, _ = pos.shape
    acc = torch.empty_like(pos)
    for s0, s1, r0, r1 in _tiles(b, n, pos.device):
        dx, dy = _separations(pos, s0, s1, r0, r1, box)
        w = dx * dx
        w += dy * dy
        w += eps2
        w = torch.rsqrt(w)
        w = w * w * w
        w *= source[s0:s1, None, :]
        acc[s0:s1, r0:r1, 0] = (w * dx).sum(-1)
        acc[s0:s1, r0:r1, 1] = (w * dy).sum(-1)
    return acc * scale[..., None]


def _pair_potential(
    pos: torch.Tensor,  # [M, N, 2] positions
    source: torch.Tensor,  # [M, N] strengths s (mass or charge)
    box: float,
    eps2: float,
) -> torch.Tensor:
    """[M] Σ_{i<j} s_i s_j / sqrt(r² + ε²) (minimum image, no self term)."""
    m, n, _ = pos.shape
    total = pos.new_zeros(m)
    for s0, s1, r0, r1 in _tiles(m, n, pos.device):
        dx, dy = _separations(pos, s0, s1, r0, r1, box)
        inv = torch.rsqrt(dx * dx + dy * dy + eps2)  # [m, r, N]
        rows = torch.arange(r0, r1, device=pos.device)
        self_pair = rows[:, None] == torch.arange(n, device=pos.device)[None, :]  # [r, N]
        inv = inv.masked_fill(self_pair, 0.0)  # no self-interaction (out of place: keeps autograd intact)
        pair = (inv * source[s0:s1, None, :]).sum(-1) * source[s0:s1, r0:r1]  # [m, r]
        total[s0:s1] += 0.5 * pair.sum(-1)  # each unordered pair is met twice
    return total
