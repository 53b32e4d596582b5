"""Equation discovery with a mechanistic-neural-network layer: a sparse polynomial ODE fitted through S-MNN.

Each node's state x ∈ R^D follows dx_i/dt = Σ_j ξ_ji φ_j(x) over a library of monomials φ of degree ≤ 2
(Lorenz: 10 terms [1, x, y, z, x², xy, xz, y², yz, z²]). Training windows of W = 50 consecutive observed states
(512 per step) are turned into the right-hand side r_t = φ(x_t) ξ, the least-squares ODE layer integrates
u' = r from the window's first state (one 1-D system per state variable, a shared left-hand side), and the loss
compares the integrated window with the observed one. Iterative thresholding (mask ← mask · [|ξ| > 0.1] every
`threshold_every` steps) makes ξ sparse (Chen et al., Scalable MNN §5.2; `shared/reference/smnn_reference.md`
§4.2). A rollout integrates the discovered ODE with the model's ODE solver, so the common metrics apply.

The layer and its training windows are in `smnn_layer`, the term library and the vector field in `smnn_library`.

Deviations from the reference notebook, both for speed on a CPU (documented in `conf/model/smnn.yaml`):
ξ is a direct parameter in a whitened basis instead of the output of a 1024-wide MLP (`param_hidden` > 0
restores the MLP), and the 1024-wide denoiser is optional (`denoiser_hidden`), residual and zero-initialised.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from mpsim.effects import Effect, EffectContext, min_delay, total
from mpsim.errors import ConfigError, IncompatibleError
from mpsim.graphs.batch import batch_graph
from mpsim.models.base import Model
from mpsim.models.capabilities import one_step_by_rollouts
from mpsim.models.layers import mlp, output_layer
from mpsim.models.smnn_layer import LAYER_METHODS, sample_windows, solve_linear_ode, uniform_step, window_history
from mpsim.models.smnn_library import (
    PolynomialField,
    equation_text,
    gather_index,
    monomial_name,
    parse_monomial,
    resolve_terms,
)
from mpsim.polynomials import monomials
from mpsim.solvers.odeint import ODESolver

if TYPE_CHECKING:
    from mpsim.data.trajectories import Inputs, Trajectories


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
        state_names: names used in the printed equations and in `extra_terms` (default: the data's state
            names; x, y, z for D = 3, else x0, x1, ... before the model is bound to data).
        extra_terms: monomials added to the library beyond `degree`, by state name: "x^3" (or "x**3",
            which the command line takes unquoted), "x y^2", "x*z" — e.g. the term `mpsim diagnose` found
            missing (`CubicStiffness` on x is "x^3"). They enter every equation; an extra term is masked when
            its typical contribution |ξ|·φ(σ) (σ: the states' standard deviations) is at most what the
            threshold allows a linear term, threshold·mean(σ), since a raw threshold of 0.1 would remove any
            cubic coefficient of realistic size.
        effects: named terms (`mpsim.effects`) added to every equation they target, with their coefficients
            trained alongside ξ (in raw units: prefer `extra_terms` for polynomial terms in a rediscovery).
        solver: integrates the discovered ODE in `rollout` and `one_step` (default dopri5).
    """

    #: constants and linear terms are in every library (degree ≥ 1): the residual loop refits them as nuisance
    represents: tuple[str, ...] = ("Bias", "LinearDamping")
    indistinguishable: tuple[str, ...] = ()
    represents_polynomials: int  # the library's degree: the residual loop projects these out

    # buffers and optional submodules (nn.Module.__getattr__ would type them as Tensor | Module)
    term_index: torch.Tensor
    mask: torch.Tensor
    precond: torch.Tensor
    deriv_scale: torch.Tensor
    initialised: torch.Tensor
    n_updates: torch.Tensor
    rounds_done: torch.Tensor
    param_in: torch.Tensor
    param_net: nn.Sequential | None
    theta: nn.Parameter | None
    denoiser: nn.Sequential | None
    terms: list[tuple[int, ...]] | None

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
        extra_terms: Sequence[str] = (),
        effects: Sequence[Effect] = (),
        solver: ODESolver | None = None,
    ) -> None:
        super().__init__(state_dim, control_dim, effects)
        if control_dim:
            raise IncompatibleError(
                f"SMNNDiscovery's library has no control terms, but the data has {control_dim} "
                "controls per node. Use a system without controls."
            )
        if solver_method not in LAYER_METHODS:
            raise ConfigError(f"model.solver_method={solver_method!r}; choose one of {LAYER_METHODS}.")
        if degree < 1 or window < 3 or window_batch < 1 or n_orders < 2 or threshold < 0:
            raise ConfigError(
                f"need model.degree >= 1, model.window >= 3, model.window_batch >= 1, model.n_orders "
                f">= 2, model.threshold >= 0; got {degree}, {window}, {window_batch}, {n_orders}, "
                f"{threshold}."
            )
        self.degree, self.window, self.window_batch, self.n_orders = degree, window, window_batch, n_orders
        self.solver_method, self.threshold, self.seed = solver_method, float(threshold), int(seed)
        self.threshold_every, self.threshold_rounds = int(threshold_every), int(threshold_rounds)
        self.solver = solver or ODESolver()
        self.represents_polynomials = int(degree)  # the residual loop projects these out (`ExpressesEffects`)
        if degree >= 3:
            self.represents = (*type(self).represents, "CubicStiffness")
        self.names_given = bool(state_names)
        default = ["x", "y", "z"] if state_dim == 3 else [f"x{i}" for i in range(state_dim)]
        self.state_names = list(state_names) if state_names else default
        if len(self.state_names) != state_dim:
            raise ConfigError(f"model.state_names has {len(self.state_names)} names for {state_dim} states.")
        self.extra_terms = [str(term) for term in extra_terms]
        self.extra = [parse_monomial(term) for term in self.extra_terms]  # [(name, power), ...] per term
        n_terms = len(monomials(state_dim, degree)) + len(self.extra)
        self.register_buffer("term_index", torch.zeros(n_terms, 1, dtype=torch.long), persistent=False)
        self._resolve_terms(strict=self.names_given)
        self.register_buffer("mask", torch.ones(n_terms, state_dim))
        # ξ = mask ⊙ deriv_scale ⊙ (precond @ θ): precond whitens the library on the first training batch
        # the identity, made without torch.eye: on the meta device (the command layer plans a model's sizes there
        # before building it) torch.eye is a Python reference that imports torch._dynamo, 1.5 s
        self.register_buffer("precond", torch.zeros(n_terms, n_terms).fill_diagonal_(1.0))
        self.register_buffer("deriv_scale", torch.ones(state_dim))
        self.register_buffer("initialised", torch.zeros((), dtype=torch.bool))
        self.register_buffer("n_updates", torch.zeros((), dtype=torch.long))
        self.register_buffer("rounds_done", torch.zeros((), dtype=torch.long))
        if param_hidden > 0:
            self.register_buffer("param_in", torch.randn(1, 64))
            self.param_net = mlp(64, param_hidden, n_terms * state_dim, 2, "relu")
            nn.init.zeros_(output_layer(self.param_net).weight)  # starts at ξ = 0, like the direct parametrisation
            self.theta = None
        else:
            self.param_net = None
            self.theta = nn.Parameter(torch.zeros(n_terms, state_dim))
        self.denoiser = None
        if denoiser_hidden > 0:
            self.denoiser = mlp(window * state_dim, denoiser_hidden, window * state_dim, 2, "relu")
            nn.init.zeros_(output_layer(self.denoiser).weight)  # var = x at the start

    def _resolve_terms(self, strict: bool) -> None:
        """Library terms from `degree` and `extra_terms` under the current state names; the gather index.

        With `strict=False` (names not known yet), extra terms whose names do not resolve wait for `bind_effects`.
        """
        self.terms = resolve_terms(self.state_dim, self.degree, self.extra_terms, self.extra, self.state_names, strict)
        if self.terms is not None:
            index = gather_index(self.terms, self.state_dim)
            self.term_index = torch.tensor(index, dtype=torch.long, device=self.term_index.device)

    def bind_effects(self, state_names: Sequence[str]) -> None:
        """Take the data's state names (unless `state_names` was given) and resolve `extra_terms` with them."""
        super().bind_effects(state_names)
        if not self.names_given and len(state_names) == self.state_dim:
            self.state_names = list(state_names)
        self._resolve_terms(strict=True)

    # ---- the library and the coefficients ------------------------------------------------------------------
    def library(self, x: torch.Tensor) -> torch.Tensor:  # x: [..., D] states (raw units)
        """[..., n_terms] monomials of x."""
        if self.terms is None:
            self._resolve_terms(strict=True)  # raises: the extra terms name unknown variables
        ext = torch.cat([x, torch.ones_like(x[..., :1])], -1)
        return ext[..., self.term_index].prod(-1)

    def _library_terms(self) -> list[tuple[int, ...]]:
        """The library's terms, resolved (as in `library`: raises if the extra terms name unknown variables)."""
        if self.terms is None:
            self._resolve_terms(strict=True)
        assert self.terms is not None  # `_resolve_terms(strict=True)` sets them or raises
        return self.terms

    def coefficients(self) -> torch.Tensor:
        """[n_terms, D] ξ in raw units: ξ[j, i] is the coefficient of term j in dx_i/dt."""
        if self.param_net is not None:
            theta = self.param_net(self.param_in).reshape(self.mask.shape)
        else:
            assert self.theta is not None  # θ is a parameter exactly when there is no param_net
            theta = self.theta
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
        phi = self.library(windows.double() / std)  # monomials of x / std
        n_terms = len(self._library_terms())
        phi = phi.reshape(-1, n_terms)
        gram = phi.mT @ phi / phi.shape[0]
        eye = torch.eye(n_terms, dtype=gram.dtype, device=gram.device)
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
        times: torch.Tensor | None = None,  # [M, W] absolute times of the windows (time-dependent effects)
        edge_index: torch.Tensor | None = None,  # [2, E] graph (effects that read neighbours)
        history: Callable[[torch.Tensor], torch.Tensor] | None = None,  # [M·W, 1] times -> [M·W, N, D] past states
    ) -> tuple[torch.Tensor, torch.Tensor]:  # [M, W, N, D] layer solution, [M, W, N, D] its input var
        """Integrate u' = φ(var) ξ (+ effects) over each window from var's first state with the least-squares
        layer. `history` gives the observed past of each window point (delayed effects only)."""
        m, w, n, d = windows.shape
        var = windows
        if self.denoiser is not None:
            flat = self.normalise(windows).permute(0, 2, 1, 3).reshape(m, n, w * d)
            var = windows + self.state_std * self.denoiser(flat).reshape(m, n, w, d).permute(0, 2, 1, 3)
        rhs = self.library(var) @ self.coefficients()  # [M, W, N, D]
        if len(self.effects):
            if min_delay(self.effects) > 0 and history is None:
                raise ConfigError("SMNNDiscovery needs the windows' history to train a DelayedFeedback effect.")
            when = torch.zeros(m, w, dtype=var.dtype, device=var.device) if times is None else times.to(var)
            flat = var.reshape(m * w, n, d)
            ei = torch.zeros(2, 0, dtype=torch.long) if edge_index is None else edge_index
            graph = batch_graph(ei.to(var.device), m * w, n, dtype=var.dtype)
            extra = total(self.effects, when.reshape(m * w, 1), flat, EffectContext(graph, history))
            rhs = rhs + extra.reshape(m, w, n, d)
        # every state variable is its own 1-D ODE u' = r (E = D = 1): one shared left-hand side, M·N·D columns
        coef = rhs.new_zeros(1, 1, 1, self.n_orders)
        coef[..., 1] = 1.0
        if isinstance(steps, torch.Tensor):  # a non-uniform grid: one left-hand side per window
            steps = steps.reshape(m, 1, 1, w - 1)
        u = solve_linear_ode(
            coef, rhs.permute(0, 2, 3, 1).unsqueeze(-1), var[:, 0].reshape(m, n, d, 1, 1, 1), steps, self.solver_method
        )  # [M, N, D, W, 1, O]
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
        steps: torch.Tensor | float
        if dt is None:  # [M, W-1] each window's own steps
            steps = t.diff()[start[:, None] + torch.arange(length - 1, device=t.device)]
        else:  # one shared step: the layer factorises a single left-hand side for all windows
            steps = dt
        if not bool(self.initialised):
            self._initialise(win, float(t[1] - t[0]))
        times = t[start[:, None] + torch.arange(length, device=t.device)] if len(self.effects) else None
        edges = batch.edge_index if batch.edge_index.dim() == 2 else batch.edge_index[0]
        history = window_history(batch.x, t, traj, length) if min_delay(self.effects) > 0 else None
        pred, var = self.integrate_windows(win, steps, times, edges, history)
        observed = batch.observed_index  # a latent state is no target
        loss = self.observed_loss(loss_fn, pred, win, observed, delta)
        if self.denoiser is not None:
            loss = loss + self.observed_loss(loss_fn, var, win, observed, delta)
        if bool(torch.isfinite(loss)):
            return loss, batch.x
        marked = batch.x.detach().clone()
        bad = ~torch.isfinite(pred.detach()).flatten(1).all(1)
        marked[traj[bad], start[bad]] = torch.nan
        return loss, marked

    @torch.no_grad()
    def after_step(self) -> None:
        """Count the step; every `threshold_every` steps mask the coefficients with |ξ| ≤ threshold (extra terms:
        see `term_thresholds`)."""
        self.n_updates += 1
        every, done = self.threshold_every, int(self.rounds_done)
        if every > 0 and done < self.threshold_rounds and int(self.n_updates) % every == 0:
            keep = self.coefficients().abs() > self.term_thresholds()[:, None].to(self.mask)
            self.mask.mul_(keep.to(self.mask))
            self.rounds_done += 1

    def term_thresholds(self) -> torch.Tensor:
        """[n_terms] the threshold of each library term: `threshold` for the degree-`degree` library (raw units,
        as the reference), and for an extra term the coefficient whose typical contribution |ξ|·φ(σ) equals
        threshold·mean(σ), with σ the states' standard deviations."""
        n_base = len(self._library_terms()) - len(self.extra)
        std = self.state_std.double()
        size = self.library(std)  # [n_terms] φ_j at the typical state size
        out = torch.full_like(size, self.threshold)
        out[n_base:] = self.threshold * std.mean() / size[n_base:].abs().clamp(min=1e-300)
        return out

    # ---- rollout and report --------------------------------------------------------------------------------
    def rollout(
        self,
        x0: torch.Tensor,  # [B, N, D] initial states (raw units)
        t: torch.Tensor,  # [T] times
        inputs: Inputs,  # only the graph, read by effects that couple neighbours (no controls)
    ) -> torch.Tensor:
        """[B, T, N, D] the discovered ODE (plus any effects) integrated from x0 with the model's ODE solver."""
        field = PolynomialField(self, self.coefficients().to(x0), self._graph(inputs.edge_index, x0))
        return self.integrate(field, x0, t.to(x0), self.solver)

    def one_step(
        self,
        x: torch.Tensor,  # [B, T, N, D] observed states (raw units)
        t: torch.Tensor,  # [T] times
        inputs: Inputs,  # only the graph [2, E] or [B, 2, E], read by effects that couple neighbours (no controls)
    ) -> torch.Tensor:
        """[B, T−1, N, D] each x_{k+1} predicted from the observed x_k by the discovered ODE.

        All B·(T−1) steps are one batched solve: the autonomous ODE over a step of length Δ_k is integrated in
        the rescaled time τ ∈ [0, 1], dx/dτ = Δ_k φ(x) ξ, so steps of any length share one call of the solver.
        """
        b, n_t, n, d = x.shape
        if n_t < 2:
            return x[:, :0]
        if min_delay(self.effects) > 0:  # a delayed term needs each step's history: step by step
            return one_step_by_rollouts(self, x, t, inputs)
        t = t.to(x)
        dt = t[1:] - t[:-1]  # [T-1]
        starts = x[:, :-1].reshape(b * (n_t - 1), n, d)
        scale = dt.expand(b, n_t - 1).reshape(-1, 1, 1)  # [B·(T−1), 1, 1] each start's step length
        start = t[:-1].expand(b, n_t - 1).reshape(-1, 1)  # [B·(T−1), 1] each start's time
        edge_index = inputs.edge_index
        if edge_index.dim() == 3:  # one graph per trajectory: repeat it for each of its steps
            edge_index = edge_index.repeat_interleave(n_t - 1, dim=0)
        field = PolynomialField(self, self.coefficients().to(x), self._graph(edge_index, starts), scale, start)
        tau = torch.tensor([0.0, 1.0], dtype=x.dtype, device=x.device)
        return self.solver(field, starts, tau)[:, 1].reshape(b, n_t - 1, n, d)

    def _graph(
        self,
        edge_index: torch.Tensor,  # [2, E] or [B, 2, E] graph
        x: torch.Tensor,  # [B, N, D] states (for the batch size, device and dtype)
    ) -> Any:
        """The batched graph for effects that read neighbours (None without effects)."""
        if not len(self.effects):
            return None
        return batch_graph(edge_index.to(x.device), x.shape[0], x.shape[1], dtype=x.dtype)

    # ---- interpretable parameters (for the residual loop's joint refit) --------------------------------------
    def _active(self) -> tuple[torch.Tensor, torch.Tensor]:
        """([P] library index, [P] equation index) of the active coefficients, equation-major."""
        eq, term = torch.nonzero(self.mask.mT > 0, as_tuple=True)
        return term, eq

    def sensitivities(
        self,
        t: torch.Tensor,  # [M, 1] or [] times (unused: the library is autonomous)
        x: torch.Tensor,  # [M, N, D] states (raw units)
        edge_index: torch.Tensor,  # unused
    ) -> torch.Tensor:
        """[M, N, D, P] ∂(dx/dt)/∂ξ for the P active coefficients: the term's monomial in its own equation."""
        term, eq = self._active()
        phi = self.library(x)[..., term]  # [M, N, P]
        onehot = torch.nn.functional.one_hot(eq, self.state_dim).mT.to(phi)  # [D, P]
        return phi[..., None, :] * onehot

    def sensitivity_names(self) -> list[str]:
        term, eq = self._active()
        terms = self._library_terms()
        return [
            f"d{self.state_names[i]}/dt: {self.monomial(terms[j])}"
            for j, i in zip(term.tolist(), eq.tolist(), strict=True)
        ]

    @torch.no_grad()
    def shift_parameters(self, shifts: dict[str, float]) -> None:
        """Add `shifts` ({"dx/dt: x z": Δ, ...}, see `sensitivity_names`) to the discovered coefficients."""
        names = self.sensitivity_names()
        term, eq = self._active()
        delta = torch.zeros_like(self.mask, dtype=torch.float64)
        for name, value in shifts.items():
            if name in names:
                k = names.index(name)
                delta[term[k], eq[k]] += value
        if not bool(delta.ne(0).any()):
            return
        # ξ = mask ⊙ s ⊙ (P θ): on the active entries, Δθ = P⁻¹ (Δξ / s)
        step = torch.linalg.solve(self.precond.double(), delta / self.deriv_scale.double())
        if self.theta is not None:
            self.theta.add_(step.to(self.theta))
        else:  # θ is the reference MLP's output: move its last bias
            assert self.param_net is not None  # θ is the MLP's output exactly when it is not a parameter
            bias = output_layer(self.param_net).bias
            bias.add_(step.reshape(-1).to(bias))

    def monomial(self, term: tuple[int, ...]) -> str:
        """The readable name of a library term ("x z", "x^3") under the model's state names."""
        return monomial_name(term, self.state_names)

    def equations(self, digits: int = 3) -> dict[str, str]:
        """Readable equations, e.g. {"x": "dx/dt = -10.000 x + 10.000 y"}: active terms that do not round to
        zero at `digits` decimals (`report()["coefficients"]` holds every active term unrounded)."""
        xi, names = self.coefficients().detach().double().cpu(), self.state_names
        terms = self._library_terms()
        out = {}
        for i, name in enumerate(names):
            parts = [
                (float(xi[j, i]), monomial_name(term, names))
                for j, term in enumerate(terms)
                if self.mask[j, i] > 0 and round(float(xi[j, i]), digits) != 0
            ]
            out[name] = f"d{name}/dt = {equation_text(parts, digits)}"
        return out

    def report(self) -> dict[str, Any]:
        """Discovered equations and coefficients (active terms, raw units) for summary.json."""
        xi, names = self.coefficients().detach().double().cpu(), self.state_names
        terms = self._library_terms()
        coefs = {
            name: {monomial_name(term, names): float(xi[j, i]) for j, term in enumerate(terms) if self.mask[j, i] > 0}
            for i, name in enumerate(names)
        }
        return {
            "equations": self.equations(),
            "coefficients": coefs,
            "library": [monomial_name(term, names) for term in terms],
            "extra_terms": self.extra_terms,
            "effects": [e.describe() for e in self.effects],
            "n_active_terms": int(self.mask.sum()),
            "threshold_rounds_done": int(self.rounds_done),
            "optimiser_steps": int(self.n_updates),
            "solver_method": self.solver_method,
            "n_orders": self.n_orders,
        }

    def report_lines(self) -> list[tuple[str, str]]:
        rows = [("discovered", eq) for eq in self.equations(4).values()]
        return rows + [("effect", e.describe()) for e in self.effects]
