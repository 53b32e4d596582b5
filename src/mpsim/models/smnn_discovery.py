"""Equation discovery with a mechanistic-neural-network layer: a sparse polynomial ODE fitted through S-MNN.

Each node's state x ∈ R^D follows dx_i/dt = Σ_j ξ_ji φ_j(x) over a library of monomials φ of degree ≤ 2
(Lorenz: 10 terms [1, x, y, z, x², xy, xz, y², yz, z²]). Training windows of W = 50 consecutive observed states
(512 per step) are turned into the right-hand side r_t = φ(x_t) ξ, the least-squares ODE layer integrates
u' = r from the window's first state (one 1-D system per state variable, a shared left-hand side), and the loss
compares the integrated window with the observed one. Iterative thresholding (mask ← mask · [|ξ| > 0.1] every
`threshold_every` steps) makes ξ sparse (Chen et al., Scalable MNN §5.2; `shared/reference/smnn_reference.md`
§4.2). A rollout integrates the discovered ODE with the model's ODE solver, so the common metrics apply.

Deviations from the reference notebook, both for speed on a CPU (documented in `conf/model/smnn.yaml`):
ξ is a direct parameter in a whitened basis instead of the output of a 1024-wide MLP (`param_hidden` > 0
restores the MLP), and the 1024-wide denoiser is optional (`denoiser_hidden`), residual and zero-initialised.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from mpsim.errors import ConfigError, IncompatibleError
from mpsim.models.base import Model
from mpsim.models.mpnode import mlp
from mpsim.solvers.mnn_dense import dense_solve, mnn_dense_solve
from mpsim.solvers.odeint import ODESolver
from mpsim.solvers.smnn import METHODS, smnn_solve

if TYPE_CHECKING:
    from mpsim.data.trajectories import Trajectories

LAYER_METHODS = (*METHODS, "dense", "mnn")


def solve_linear_ode(
    coefficients: torch.Tensor,  # [*batch, T or 1, E, D, O] equation coefficients
    rhs: torch.Tensor,  # [*batch, T, E] equation right-hand sides
    init: torch.Tensor,  # [*batch, 1, D, I] initial values at the first step
    steps: torch.Tensor | float,  # [*batch, T-1] or one shared step
    method: str,
) -> torch.Tensor:  # [*batch, T, D, O]
    """The MNN layer: least-squares solution of a linear ODE with any of the solvers.

    "banded"/"cyclic"/"auto" are the linear-time S-MNN solves, "dense" the same S-MNN system with a dense
    Cholesky, "mnn" the original MNN with a slack variable and central smoothness rows (spec §6.1).
    """
    if method == "dense":
        return dense_solve(coefficients, rhs, init, steps)
    if method == "mnn":
        return mnn_dense_solve(coefficients, rhs, init, steps)[0]
    return smnn_solve(coefficients, rhs, init, steps, method=method)


def monomials(n_vars: int, degree: int) -> list[tuple[int, ...]]:
    """Variable-index tuples of every monomial of degree ≤ `degree`, graded (pysindy/reference order)."""
    return [c for d in range(degree + 1) for c in itertools.combinations_with_replacement(range(n_vars), d)]


def monomial_name(term: tuple[int, ...], names: Sequence[str]) -> str:
    """"1", "x", "x^2", "x z" for the index tuple of a monomial."""
    if not term:
        return "1"
    return " ".join(names[v] + (f"^{p}" if p > 1 else "") for v, p in sorted({v: term.count(v) for v in term}.items()))


def uniform_step(t: torch.Tensor) -> float | None:  # t: [T] times
    """The grid's step when `t` is uniform (to 1e-6 relative), else None."""
    dt = t[1:] - t[:-1]
    return float(dt[0]) if bool(((dt - dt[0]).abs() <= 1e-6 * dt[0].abs()).all()) else None


def sample_windows(
    x: torch.Tensor,  # [B, T, N, D] trajectories
    n_windows: int,
    length: int,
    generator: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # [M, W, N, D] windows, [M] trajectory, [M] start
    """`n_windows` random windows of `length` consecutive steps (uniform over trajectory and start)."""
    traj = torch.randint(x.shape[0], (n_windows,), generator=generator).to(x.device)
    start = torch.randint(x.shape[1] - length + 1, (n_windows,), generator=generator).to(x.device)
    steps = start[:, None] + torch.arange(length, device=x.device)
    return x[traj[:, None], steps], traj, start


class _PolynomialField(nn.Module):
    """dx/dt = φ(x) ξ for the ODE solver (ξ fixed during one rollout)."""

    def __init__(self, library: Callable[[torch.Tensor], torch.Tensor], xi: torch.Tensor) -> None:
        super().__init__()
        self.library, self.xi = library, xi

    def forward(self, t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:  # t: [], x: [B, N, D]
        return self.library(x) @ self.xi


class SMNNDiscovery(Model):
    """Sparse polynomial equation discovery through an S-MNN (or dense MNN) layer.

    Args:
        state_dim: D, state variables per node (set from the data).
        control_dim: must be 0 (the library has no control terms).
        degree: polynomial degree of the library (reference: 2).
        window: W, steps per training window (reference: 50; shorter trajectories use their full length).
        window_batch: windows per optimiser step (reference: 512), drawn from the trainer's batch of
            trajectories (all nodes of a window are used).
        n_orders: O, derivative orders the layer solves for (reference: 3). With O = 3 and h = 0.01 the
            layer's discretisation biases the Lorenz coefficients by up to 3 % (a4 ≈ −0.97) unless a
            denoiser absorbs it; O = 4 brings the bias below 0.2 %.
        solver_method: banded | cyclic | auto (linear-time S-MNN), dense (same system, dense Cholesky) or
            mnn (original MNN with a slack variable).
        threshold: coefficients with |ξ| ≤ threshold (raw units) are masked to zero at each round.
        threshold_every: optimiser steps between thresholding rounds (reference: 400 epochs × 19 steps).
        threshold_rounds: maximum number of rounds (reference: 9); 0 disables thresholding.
        param_hidden: 0 makes the coefficients direct parameters; > 0 produces them with the reference's
            MLP from a fixed random input (64 → param_hidden → param_hidden → |library|·D).
        denoiser_hidden: 0 uses the observed window as the layer's input; > 0 adds the reference's
            denoiser (an MLP on the flattened window, here residual: var = x + std · net(x)), trained with
            an extra loss on var.
        seed: seed of the window sampling (combined with the step count, so a resumed run draws the same
            windows).
        state_names: names used in the printed equations (default: x, y, z for D = 3, else x0, x1, ...).
        solver: integrates the discovered ODE in `rollout` (default dopri5).
    """

    def __init__(
        self,
        state_dim: int,
        control_dim: int = 0,
        degree: int = 2,
        window: int = 50,
        window_batch: int = 512,
        n_orders: int = 3,
        solver_method: str = "auto",
        threshold: float = 0.1,
        threshold_every: int = 7600,
        threshold_rounds: int = 9,
        param_hidden: int = 0,
        denoiser_hidden: int = 0,
        seed: int = 0,
        state_names: Sequence[str] | None = None,
        solver: ODESolver | None = None,
    ) -> None:
        super().__init__(state_dim, control_dim)
        if control_dim:
            raise IncompatibleError(f"SMNNDiscovery's library has no control terms, but the data has {control_dim} "
                                    "controls per node. Use a system without controls.")
        if solver_method not in LAYER_METHODS:
            raise ConfigError(f"model.solver_method={solver_method!r}; choose one of {LAYER_METHODS}.")
        if degree < 1 or window < 3 or window_batch < 1 or n_orders < 2 or threshold < 0:
            raise ConfigError(f"need model.degree >= 1, model.window >= 3, model.window_batch >= 1, model.n_orders "
                              f">= 2, model.threshold >= 0; got {degree}, {window}, {window_batch}, {n_orders}, "
                              f"{threshold}.")
        self.degree, self.window, self.window_batch, self.n_orders = degree, window, window_batch, n_orders
        self.solver_method, self.threshold, self.seed = solver_method, float(threshold), int(seed)
        self.threshold_every, self.threshold_rounds = int(threshold_every), int(threshold_rounds)
        self.solver = solver or ODESolver()
        self.terms = monomials(state_dim, degree)
        n_terms = len(self.terms)
        # library as a gather from [x, 1]: the constant slot pads lower-degree terms (gradient-safe, no pow)
        index = [list(term) + [state_dim] * (degree - len(term)) for term in self.terms]
        self.register_buffer("term_index", torch.tensor(index, dtype=torch.long), persistent=False)
        self.register_buffer("mask", torch.ones(n_terms, state_dim))
        # ξ = mask ⊙ deriv_scale ⊙ (precond @ θ): precond whitens the library on the first training batch
        self.register_buffer("precond", torch.eye(n_terms))
        self.register_buffer("deriv_scale", torch.ones(state_dim))
        self.register_buffer("initialised", torch.zeros((), dtype=torch.bool))
        self.register_buffer("n_updates", torch.zeros((), dtype=torch.long))
        self.register_buffer("rounds_done", torch.zeros((), dtype=torch.long))
        if param_hidden > 0:
            self.register_buffer("param_in", torch.randn(1, 64))
            self.param_net = mlp(64, param_hidden, n_terms * state_dim, 2, "relu")
            nn.init.zeros_(self.param_net[-1].weight)  # starts at ξ = 0, like the direct parametrisation
            self.theta = None
        else:
            self.param_net = None
            self.theta = nn.Parameter(torch.zeros(n_terms, state_dim))
        self.denoiser = None
        if denoiser_hidden > 0:
            self.denoiser = mlp(window * state_dim, denoiser_hidden, window * state_dim, 2, "relu")
            nn.init.zeros_(self.denoiser[-1].weight)  # var = x at the start
        default = ["x", "y", "z"] if state_dim == 3 else [f"x{i}" for i in range(state_dim)]
        self.state_names = list(state_names) if state_names else default
        if len(self.state_names) != state_dim:
            raise ConfigError(f"model.state_names has {len(self.state_names)} names for {state_dim} states.")

    # ---- the library and the coefficients ------------------------------------------------------------------
    def library(self, x: torch.Tensor) -> torch.Tensor:  # x: [..., D] states (raw units)
        """[..., n_terms] monomials of x."""
        ext = torch.cat([x, torch.ones_like(x[..., :1])], -1)
        return ext[..., self.term_index].prod(-1)

    def coefficients(self) -> torch.Tensor:
        """[n_terms, D] ξ in raw units: ξ[j, i] is the coefficient of term j in dx_i/dt."""
        theta = self.theta if self.param_net is None else self.param_net(self.param_in).reshape(self.mask.shape)
        return self.mask * self.deriv_scale * (self.precond @ theta)

    @torch.no_grad()
    def _initialise(
        self,
        windows: torch.Tensor,  # [M, W, N, D] observed windows
        dt: float,
    ) -> None:
        """Whiten the library on the first training batch (a data-dependent reparametrisation).

        The monomials of Lorenz states are strongly correlated (z ≈ 25 ± 9, so 1, z, z² nearly collinear):
        with ξ as plain parameters Adam needs ~10⁴ steps to separate them. Fitting θ in a basis in which the
        library's Gram matrix is the identity (ξ = s ⊙ P θ, P = L⁻ᵀ with G = LLᵀ, s the scale of each dx/dt)
        finds the Lorenz support in ~300 steps. The monomials are scaled per variable (never centred), so a
        zero in ξ is a zero in raw units and the thresholding stays meaningful.
        """
        std = self.state_std.double()
        phi = self.library(windows.double() / std).reshape(-1, len(self.terms))  # monomials of x / std
        gram = phi.mT @ phi / phi.shape[0]
        eye = torch.eye(len(self.terms), dtype=gram.dtype, device=gram.device)
        gram = gram + 1e-12 * gram.diagonal().mean() * eye  # a constant state would make it singular
        whiten = torch.linalg.solve_triangular(torch.linalg.cholesky(gram).mT, eye, upper=True)
        term_scale = self.library(std)  # φ_j(x / std) = φ_j(x) / term_scale_j
        self.precond.copy_(whiten / term_scale[:, None])
        rate = (windows[:, 1:] - windows[:, :-1]).double().reshape(-1, self.state_dim) / dt
        scale = rate.std(0) if rate.shape[0] > 1 else torch.ones_like(std)
        self.deriv_scale.copy_(torch.where(scale > 0, scale, torch.ones_like(scale)))
        self.initialised.fill_(True)

    # ---- training ------------------------------------------------------------------------------------------
    def integrate_windows(
        self,
        windows: torch.Tensor,  # [M, W, N, D] observed windows (raw units)
        steps: torch.Tensor | float,  # [M, W-1] step sizes per window, or one shared step
    ) -> tuple[torch.Tensor, torch.Tensor]:  # [M, W, N, D] layer solution, [M, W, N, D] its input var
        """Integrate u' = φ(var) ξ over each window from var's first state with the least-squares layer."""
        m, w, n, d = windows.shape
        var = windows
        if self.denoiser is not None:
            flat = self.normalise(windows).permute(0, 2, 1, 3).reshape(m, n, w * d)
            var = windows + self.state_std * self.denoiser(flat).reshape(m, n, w, d).permute(0, 2, 1, 3)
        rhs = self.library(var) @ self.coefficients()  # [M, W, N, D]
        # every state variable is its own 1-D ODE u' = r (E = D = 1): one shared left-hand side, M·N·D columns
        coef = rhs.new_zeros(1, 1, 1, self.n_orders)
        coef[..., 1] = 1.0
        if isinstance(steps, torch.Tensor):  # a non-uniform grid: one left-hand side per window
            steps = steps.reshape(m, 1, 1, w - 1)
        u = solve_linear_ode(coef, rhs.permute(0, 2, 3, 1).unsqueeze(-1), var[:, 0].reshape(m, n, d, 1, 1, 1),
                             steps, self.solver_method)  # [M, N, D, W, 1, O]
        return u[..., 0, 0].permute(0, 3, 1, 2), var

    def training_loss(
        self,
        batch: Trajectories,
        t: torch.Tensor,  # [T] times
        loss_fn: Callable[..., torch.Tensor],
        delta: float = 1.0,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Loss of the layer's solution on `window_batch` random windows of the batch (normalised units).

        Returns (loss, [B, T, N, D] the batch itself, with NaN where a window's solution was not finite):
        windows do not map onto whole trajectories, so this stands in for the prediction in the trainer's
        divergence message.
        """
        length = min(self.window, batch.n_times)
        gen = torch.Generator().manual_seed(self.seed * 1_000_003 + int(self.n_updates))
        win, traj, start = sample_windows(batch.x, self.window_batch, length, gen)
        dt = uniform_step(t)
        if dt is None:  # [M, W-1] each window's own steps
            steps = t.diff()[start[:, None] + torch.arange(length - 1, device=t.device)]
        else:  # one shared step: the layer factorises a single left-hand side for all windows
            steps = dt
        if not bool(self.initialised):
            self._initialise(win, float(t[1] - t[0]))
        pred, var = self.integrate_windows(win, steps)
        loss = loss_fn(self.normalise(pred), self.normalise(win), delta)
        if self.denoiser is not None:
            loss = loss + loss_fn(self.normalise(var), self.normalise(win), delta)
        if bool(torch.isfinite(loss)):
            return loss, batch.x
        marked = batch.x.detach().clone()
        bad = ~torch.isfinite(pred.detach()).flatten(1).all(1)
        marked[traj[bad], start[bad]] = torch.nan
        return loss, marked

    @torch.no_grad()
    def after_step(self) -> None:
        """Count the step; every `threshold_every` steps mask the coefficients with |ξ| ≤ threshold."""
        self.n_updates += 1
        every, done = self.threshold_every, int(self.rounds_done)
        if every > 0 and done < self.threshold_rounds and int(self.n_updates) % every == 0:
            self.mask.mul_((self.coefficients().abs() > self.threshold).to(self.mask))
            self.rounds_done += 1

    # ---- rollout and report --------------------------------------------------------------------------------
    def rollout(
        self,
        x0: torch.Tensor,  # [B, N, D] initial states (raw units)
        t: torch.Tensor,  # [T] times
        edge_index: torch.Tensor,  # unused: every node follows the same discovered ODE
        u: torch.Tensor | None = None,  # unused: no controls
        node_features: torch.Tensor | None = None,  # unused
        meta: dict[str, Any] | None = None,  # unused
    ) -> torch.Tensor:
        """[B, T, N, D] the discovered ODE integrated from x0 with the model's ODE solver."""
        field = _PolynomialField(self.library, self.coefficients().to(x0))
        return self.solver(field, x0, t.to(x0))

    def equations(self, digits: int = 3) -> dict[str, str]:
        """Readable equations, e.g. {"x": "dx/dt = -10.000 x + 10.000 y"}: active terms that do not round to
        zero at `digits` decimals (`report()["coefficients"]` holds every active term unrounded)."""
        xi, names = self.coefficients().detach().double().cpu(), self.state_names
        out = {}
        for i, name in enumerate(names):
            parts = [(float(xi[j, i]), monomial_name(term, names)) for j, term in enumerate(self.terms)
                     if self.mask[j, i] > 0 and round(float(xi[j, i]), digits) != 0]
            text = ""
            for k, (c, term) in enumerate(parts):
                sign = ("-" if c < 0 else "") if k == 0 else (" - " if c < 0 else " + ")
                text += f"{sign}{abs(c):.{digits}f}" + ("" if term == "1" else f" {term}")
            out[name] = f"d{name}/dt = {text or '0'}"
        return out

    def report(self) -> dict[str, Any]:
        """Discovered equations and coefficients (active terms, raw units) for summary.json."""
        xi, names = self.coefficients().detach().double().cpu(), self.state_names
        coefs = {name: {monomial_name(term, names): float(xi[j, i]) for j, term in enumerate(self.terms)
                        if self.mask[j, i] > 0} for i, name in enumerate(names)}
        return {"equations": self.equations(), "coefficients": coefs,
                "library": [monomial_name(term, names) for term in self.terms],
                "n_active_terms": int(self.mask.sum()), "threshold_rounds_done": int(self.rounds_done),
                "optimiser_steps": int(self.n_updates), "solver_method": self.solver_method,
                "n_orders": self.n_orders}

    def report_lines(self) -> list[tuple[str, str]]:
        return [("discovered", eq) for eq in self.equations(4).values()]
