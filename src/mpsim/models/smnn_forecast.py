"""Forecasting with a mechanistic-neural-network layer: an encoder writes a linear ODE, S-MNN solves it.

For every node, an encoder (MLP shared by all nodes) reads the last K observed states of the node, the mean of
its neighbours' windows and, where the system has controls, the controls over the window and the next chunk.
It writes a linear ODE for the next `chunk` steps in normalised units, with time measured in sample steps:

    u'(τ) = A u(τ) + r_τ,   u(0) = the last state,   A ∈ R^{D×D} per node, r_τ ∈ R^D per step,

the S-MNN layer solves it (least squares over values and derivatives with Taylor smoothness rows; spec §1),
and the solution is the continuation. Longer horizons repeat this autoregressively on the newest K states,
as the reference's KdV forecaster does (spec §4.4). The encoder's output layer starts at zero (A = 0, r = 0),
so an untrained model is the persistence forecast, and training is measured against that baseline.
Because the encoder is per node and aggregates neighbours by a mean, a model runs on any graph. With
`whole_state=true` the N nodes' states are instead one state of size N·D (a dense A couples every variable of
every node): no graph structure is assumed, and the model runs only on graphs of `n_nodes` nodes.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from mpsim.data.trajectories import Inputs
from mpsim.errors import ConfigError
from mpsim.graphs.batch import batch_graph, mean_aggregate
from mpsim.models.base import Model
from mpsim.models.layers import mlp, output_layer
from mpsim.models.smnn_layer import LAYER_METHODS, solve_linear_ode, uniform_step
from mpsim.solvers.odeint import ODESolver

if TYPE_CHECKING:
    from mpsim.data.trajectories import Trajectories


class SMNNForecaster(Model):
    """Window → linear ODE → S-MNN continuation, per node.

    Args:
        state_dim: D, state variables per node (set from the data).
        control_dim: C, controls per node (set from the data).
        context_steps: K, observed states the encoder reads (the first K states of a test trajectory are
            given; errors are measured from step K on).
        chunk: steps predicted per solve (reference KdV: 9-10).
        hidden: encoder width.
        n_hidden_layers: encoder hidden layers.
        activation: encoder activation (tanh, relu, softplus, silu, gelu).
        n_orders: O, derivative orders in the layer (u, u', u'' for 3).
        neighbours: feed the mean of the neighbours' windows to the encoder (coupled systems).
        solver_method: banded | cyclic | auto | dense | mnn (see `mpsim.models.smnn_discovery`).
        train_steps: predicted steps per training sample, from a random start in each trajectory (None: the
            whole trajectory from its first K states, single shooting).
        seed: seed of the random training starts (combined with the step count, so a resumed run matches).
        whole_state: one linear ODE for the flattened state of all `n_nodes` nodes instead of one per node.
        n_nodes: N, required with `whole_state` (the encoder's size depends on it).
        solver: unused (the layer is the solver); accepted because every model receives one.
    """

    # submodule and buffer (nn.Module.__getattr__ would type them as Tensor | Module)
    encoder: nn.Sequential
    n_updates: torch.Tensor

    def __init__(
        self,
        state_dim: int,
        control_dim: int = 0,
        context_steps: int = 10,
        chunk: int = 10,
        hidden: int = 128,
        n_hidden_layers: int = 2,
        activation: str = "tanh",
        n_orders: int = 3,
        neighbours: bool = True,
        solver_method: str = "auto",
        train_steps: int | None = None,
        seed: int = 0,
        whole_state: bool = False,
        n_nodes: int | None = None,
        solver: ODESolver | None = None,
    ) -> None:
        super().__init__(state_dim, control_dim)
        if whole_state and (n_nodes is None or n_nodes < 1):
            raise ConfigError(
                "model.whole_state=true needs model.n_nodes=<nodes of the system> (the encoder reads "
                "all nodes' states at once)."
            )
        if solver_method not in LAYER_METHODS:
            raise ConfigError(f"model.solver_method={solver_method!r}; choose one of {LAYER_METHODS}.")
        if context_steps < 1 or chunk < 1 or n_orders < 2 or (train_steps is not None and train_steps < 1):
            raise ConfigError(
                f"need model.context_steps >= 1, model.chunk >= 1, model.n_orders >= 2 and "
                f"model.train_steps >= 1 or null; got {context_steps}, {chunk}, {n_orders}, "
                f"{train_steps}."
            )
        self.context_steps, self.chunk, self.n_orders = int(context_steps), int(chunk), int(n_orders)
        self.neighbours, self.solver_method, self.train_steps = bool(neighbours), solver_method, train_steps
        self.seed = int(seed)
        self.whole_state, self.n_nodes = bool(whole_state), n_nodes
        self.transfers_across_graphs = not self.whole_state
        width = n_nodes if self.whole_state and n_nodes is not None else 1  # nodes folded into one state
        if self.whole_state:
            self.neighbours = False
        d, k, c = state_dim * width, self.context_steps, control_dim * width
        n_in = k * d * (2 if self.neighbours else 1) + d + (k + self.chunk) * c
        self.encoder = mlp(n_in, hidden, d * d + (self.chunk + 1) * d, n_hidden_layers, activation)
        nn.init.zeros_(output_layer(self.encoder).weight)  # A = 0, r = 0: the untrained model is persistence
        self.register_buffer("n_updates", torch.zeros((), dtype=torch.long))

    # ---- one chunk ---------------------------------------------------------------------------------------
    def encode(
        self,
        window: torch.Tensor,  # [B, K, N, D] the newest K states, normalised
        graph: Any,  # BatchedGraph of the B graphs
        controls: torch.Tensor | None,  # [B, K + chunk, N, C] controls over the window and the chunk
    ) -> tuple[torch.Tensor, torch.Tensor]:  # A [B, N, D, D], r [B, N, chunk + 1, D]
        """The linear ODE of the next chunk for every node."""
        b, k, n, d = window.shape
        last = window[:, -1]  # [B, N, D]
        # the shape of the recent past relative to the present state, plus the present state itself (the
        # dynamics of e.g. a pendulum depend on where it is, not only on how it moved)
        own = (window - last[:, None]).permute(0, 2, 1, 3).reshape(b, n, k * d)
        feats = [own, last]
        if self.neighbours:
            feats.append(mean_aggregate(window.permute(0, 2, 1, 3).reshape(b, n, k * d), graph))
        if controls is not None:
            feats.append(controls.permute(0, 2, 1, 3).reshape(b, n, -1))
        out = self.encoder(torch.cat(feats, -1))
        # |A_ij| < 2/(chunk·D) bounds every row sum of |A| by 2/chunk, so u' = Au grows by at most e² over a
        # chunk whatever the state size (13 quadrotor states with |A_ij| < 1/chunk allowed e^13): an unbounded A
        # lets one bad encoder output blow a rollout up exponentially, and its gradient with it
        A = torch.tanh(out[..., : d * d]).reshape(b, n, d, d) * (2.0 / (self.chunk * d))
        return A, out[..., d * d :].reshape(b, n, self.chunk + 1, d)

    def solve_chunk(
        self,
        A: torch.Tensor,  # [B, N, D, D] linear part
        r: torch.Tensor,  # [B, N, L + 1, D] forcing at the chunk's L + 1 points
        last: torch.Tensor,  # [B, N, D] normalised state the chunk starts from
        steps: torch.Tensor | float,  # [L] step sizes in units of the sample step, or one shared step
    ) -> torch.Tensor:  # [B, L, N, D] the next L normalised states
        """Solve u' = A u + r_τ, u(0) = last, over the chunk with the least-squares layer."""
        b, n, d, _ = A.shape
        # equation e: u'_e − Σ_d A_ed u_d = r_e (orders beyond 1 only enter through smoothness)
        coef = A.new_zeros(b, n, 1, d, d, self.n_orders)
        coef[..., 0] = -A[:, :, None]
        coef[..., 1] = torch.eye(d, dtype=A.dtype, device=A.device)
        u = solve_linear_ode(coef, r, last[:, :, None, :, None], steps, self.solver_method)  # [B, N, L+1, D, O]
        return u[:, :, 1:, :, 0].transpose(1, 2)

    # ---- rollout -----------------------------------------------------------------------------------------
    def rollout(
        self,
        x0: torch.Tensor,  # [B, K, N, D] first K observed states (raw units), or [B, N, D] when K = 1
        t: torch.Tensor,  # [T] times
        inputs: Inputs,  # graph [2, E] or [B, 2, E], controls [B, T, N, C]
    ) -> torch.Tensor:
        """[B, T, N, D]: the K given states, then chunk after chunk of S-MNN continuation."""
        u = inputs.u
        context = x0[:, None] if x0.dim() == 3 else x0
        b, k, n, d = context.shape
        if k != self.context_steps:
            fix = (
                f" The records hold {k} time points: use data.horizon >= {self.context_steps} or a smaller "
                "model.context_steps."
                if k < self.context_steps
                else ""
            )
            raise ConfigError(f"SMNNForecaster reads {self.context_steps} context states; got {k}.{fix}")
        if t.shape[0] <= k:
            return context[:, : t.shape[0]]
        if self.whole_state:  # one node whose state is every node's state
            if n != self.n_nodes:
                raise ConfigError(
                    f"SMNNForecaster(whole_state=true) was built for {self.n_nodes} nodes; the data has "
                    f"{n}. Use whole_state=false (per node) to run on other graphs."
                )
            flat_u = None if u is None else u.flatten(2)[:, :, None]  # [B, T, 1, N·C]
            no_edges = torch.zeros(2, 0, dtype=torch.long, device=context.device)
            pred = self._rollout_flat(self.normalise(context).reshape(b, k, 1, n * d), t, no_edges, flat_u)
            pred = pred.reshape(b, -1, n, d)
        else:
            pred = self._rollout_flat(self.normalise(context), t, inputs.edge_index, u)
        return torch.cat([context, self.denormalise(pred)], 1)  # the context as given

    def _rollout_flat(
        self,
        context: torch.Tensor,  # [B, K, N', D'] normalised context (N' = 1, D' = N·D with whole_state)
        t: torch.Tensor,  # [T] times
        edge_index: torch.Tensor,  # [2, E] or [B, 2, E]
        u: torch.Tensor | None,  # [B, T, N', C'] controls
    ) -> torch.Tensor:  # [B, T − K, N', D'] normalised predictions after the context
        """Chunk after chunk of S-MNN continuation in normalised units."""
        b, k, n, _ = context.shape
        t = t.to(context)
        n_t = t.shape[0]
        graph = batch_graph(edge_index.to(context.device), b, n, dtype=context.dtype)
        dt = uniform_step(t) if n_t > 1 else 1.0
        scaled = t.diff() / (t[1] - t[0]) if n_t > 1 else t  # steps in units of the first sample step
        states = list(context.unbind(1))  # one [B, N, D] per time step
        while len(states) < n_t:
            s, length = len(states) - 1, min(self.chunk, n_t - len(states))
            controls = None
            if u is not None and self.control_dim:
                idx = (torch.arange(s - k + 1, s + self.chunk + 1, device=u.device)).clamp(0, n_t - 1)
                controls = u[:, idx].to(context)  # past the end: the last control held
            A, r = self.encode(torch.stack(states[-k:], 1), graph, controls)
            steps = 1.0 if dt is not None else scaled[s : s + length]
            nxt = self.solve_chunk(A, r[:, :, : length + 1], states[-1], steps)
            states.extend(nxt.unbind(1))
        return torch.stack(states[k:n_t], 1)

    # ---- training ----------------------------------------------------------------------------------------
    def training_loss(
        self,
        batch: Trajectories,
        t: torch.Tensor,  # [T] times
        loss_fn: Callable[..., torch.Tensor],
        delta: float = 1.0,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Loss on the predicted steps of each trajectory (normalised units), from a random start when
        `train_steps` is set (more distinct training windows per epoch than single shooting from t0)."""
        x, k = batch.x, self.context_steps
        length = batch.n_times if self.train_steps is None else min(batch.n_times, k + self.train_steps)
        sub_u = batch.u
        if length < batch.n_times and uniform_step(t) is not None:
            gen = torch.Generator().manual_seed(self.seed * 1_000_003 + int(self.n_updates))
            start = torch.randint(batch.n_times - length + 1, (len(batch),), generator=gen).to(x.device)
            idx = start[:, None] + torch.arange(length, device=x.device)  # [B, length]
            rows = torch.arange(len(batch), device=x.device)[:, None]
            x = x[rows, idx]
            sub_u = None if batch.u is None else batch.u[rows, idx]
        else:
            x = x[:, :length]
            sub_u = None if sub_u is None else sub_u[:, :length]
        pred = self.rollout(x[:, :k], t[:length], Inputs(batch.edge_index, sub_u))
        # the first K − 1 steps are given; loss over the last context state and everything predicted
        return self.observed_loss(loss_fn, pred[:, k - 1 :], x[:, k - 1 :], batch.observed_index, delta), pred

    @torch.no_grad()
    def after_step(self) -> None:
        self.n_updates += 1

    def report(self) -> dict[str, Any]:
        return {
            "context_steps": self.context_steps,
            "chunk": self.chunk,
            "solver_method": self.solver_method,
            "n_orders": self.n_orders,
            "whole_state": self.whole_state,
        }
