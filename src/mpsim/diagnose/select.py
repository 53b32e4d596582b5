"""Sparse selection of candidate terms: forward stepwise least squares with the Bayesian information
criterion, explained variance per candidate, and a bootstrap over trajectories.

Each candidate is a group of columns (a forcing has two: sin and cos) that enters or leaves as a whole.
Rows are (trajectory, step, node) samples of one state variable's residual. Optional `base` columns are
always in the fit and never named: for a white-box model they are the sensitivities of its own equations to
its fitted parameters, so that a parameter that partly absorbed a missing effect during training is refit
alongside the candidates instead of being mistaken for one. Shares of "the residual" are then shares of what
is left after the base fit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch


def lstsq(x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, float]:  # x: [n, p], y: [n]
    """(coefficients [p], residual sum of squares) of y on the columns of x plus an intercept-free fit."""
    if x.shape[1] == 0:
        return x.new_zeros(0), float(y.pow(2).sum())
    scale = x.norm(dim=0).clamp(min=1e-300)  # column scaling for conditioning
    # SVD-based driver: nuisance bases can be exactly collinear (e.g. −x and the monomial x)
    sol = torch.linalg.lstsq(x / scale, y[:, None], driver="gelsd").solution[:, 0] / scale
    return sol, float((y - x @ sol).pow(2).sum())


@dataclass
class Selection:
    """Result of a stepwise selection.

    Attributes:
        groups: indices of the selected groups, in the order they entered.
        coef: {group index: fitted coefficients} of the final joint fit.
        gains: {group index: share of the residual sum of squares removed when the group entered}.
        r2: share of the residual sum of squares explained by the final model.
        bic_path: BIC after each entry (the first value is the empty model's).
        total: residual sum of squares after the base fit (what the shares are shares of).
    """

    groups: list[int]
    coef: dict[int, list[float]]
    gains: dict[int, float]
    r2: float
    bic_path: list[float]
    total: float = 0.0


def project_out(
    base: torch.Tensor,  # [n, q] nuisance columns
    *arrays: torch.Tensor,  # each [n] or [n, k]
    rtol: float = 1e-9,
) -> list[torch.Tensor]:
    """Each array minus its least-squares fit on `base` (an orthonormal basis of the base's column space,
    rank-revealing, so collinear nuisance columns are harmless). Fitting on projected data is the same as
    fitting with the base columns always included."""
    scale = base.norm(dim=0).clamp(min=1e-300)
    u, s, _ = torch.linalg.svd(base / scale, full_matrices=False)
    q = u[:, s > rtol * s.max()] if s.numel() else u[:, :0]
    out = []
    for a in arrays:
        a2 = a[:, None] if a.dim() == 1 else a
        out.append((a2 - q @ (q.T @ a2)).reshape(a.shape))
    return out


def _base_cols(base: torch.Tensor | None, y: torch.Tensor) -> torch.Tensor:
    return y.new_zeros(y.numel(), 0) if base is None else base


def _gram_fit(gram: torch.Tensor, xty: torch.Tensor, yty: float, cols: list[int]) -> tuple[torch.Tensor, float]:
    """(coefficients, RSS) of the least-squares fit on columns `cols`, from the Gram matrix XᵀX [P, P], Xᵀy [P]
    and yᵀy: a small rank-revealing solve on scaled columns, whatever the number of rows."""
    if not cols:
        return gram.new_zeros(0), yty
    idx = torch.as_tensor(cols)
    g, c = gram[idx][:, idx], xty[idx]
    scale = g.diagonal().clamp(min=1e-300).sqrt()
    sol = torch.linalg.lstsq(g / scale[:, None] / scale[None, :], (c / scale)[:, None], driver="gelsd").solution[:, 0]
    sol = sol / scale
    return sol, max(float(yty - 2 * sol @ c + sol @ g @ sol), 0.0)


def _stepwise_gram(
    gram: torch.Tensor,
    xty: torch.Tensor,
    yty: float,
    n: int,
    spans: list[list[int]],
    base: list[int],
    max_terms: int,
    same: list[int] | None = None,
) -> Selection:
    """Forward stepwise BIC selection on precomputed normal equations (`spans`: each group's column indices).

    Groups with one label in `same` are one effect written two ways (a drive with a phase per recording and the
    shared-phase drive at nearly the same frequency): once one is chosen the others are not offered, since the
    two together are nearly collinear and their coefficients would cancel each other (case 2: 77 and −67)."""
    labels = list(range(len(spans))) if same is None else list(same)
    _, total = _gram_fit(gram, xty, yty, base)
    if total <= 0 or n == 0:
        return Selection([], {}, {}, 0.0, [], max(total, 0.0))
    chosen: list[int] = []
    rss = total
    bic = n * math.log(rss / n) + len(base) * math.log(n)
    path, gains = [bic], {}
    while len(chosen) < max_terms:
        best = None
        taken = {labels[i] for i in chosen}
        for g in range(len(spans)):  # the group that lowers the BIC most (a wide group pays for its columns)
            if labels[g] in taken:
                continue
            cols = base + [c for i in [*chosen, g] for c in spans[i]]
            _, r = _gram_fit(gram, xty, yty, cols)
            b = n * math.log(max(r, 1e-300) / n) + len(cols) * math.log(n)
            if best is None or b < best[2]:
                best = (g, r, b)
        if best is None:
            break
        g, r, new_bic = best
        if new_bic >= bic:
            break
        gains[g] = (rss - r) / total
        chosen.append(g)
        rss, bic = r, new_bic
        path.append(bic)
    coef: dict[int, list[float]] = {}
    if chosen:
        sol, rss = _gram_fit(gram, xty, yty, base + [c for i in chosen for c in spans[i]])
        at = len(base)
        for g in chosen:
            k = len(spans[g])
            coef[g] = [float(v) for v in sol[at : at + k]]
            at += k
    return Selection(chosen, coef, gains, 1 - rss / total, path, total)


def _design(groups: list[torch.Tensor], base: torch.Tensor | None) -> tuple[torch.Tensor, list[list[int]], list[int]]:
    """(all columns side by side, each group's column indices, the base's column indices)."""
    parts = ([] if base is None else [base]) + list(groups)
    q = 0 if base is None else base.shape[-1]
    spans, at = [], q
    for g in groups:
        spans.append(list(range(at, at + g.shape[-1])))
        at += g.shape[-1]
    return torch.cat(parts, dim=-1), spans, list(range(q))


def stepwise_bic(
    y: torch.Tensor,  # [n] residual samples
    groups: list[torch.Tensor],  # each [n, k_g] basis columns of one candidate
    max_terms: int = 6,
    base: torch.Tensor | None = None,  # [n, q] columns always in the fit (never selected or named)
    same: list[int] | None = None,  # per group, a label: groups with one label exclude each other
) -> Selection:
    """Forward stepwise selection: add the group that lowers the BIC = n·log(RSS/n) + p·log(n) most, while it
    decreases (a group of many columns, a drive with a phase per recording, must pay for them). The fits run on the normal equations (one pass over the
    rows), so the cost does not grow with the number of samples per step."""
    x, spans, base_cols = _design(groups, base)
    gram, xty, yty = x.T @ x, x.T @ y, float(y @ y)
    return _stepwise_gram(gram, xty, yty, y.numel(), spans, base_cols, max_terms, same)


def explained_alone(y: torch.Tensor, groups: list[torch.Tensor], base: torch.Tensor | None = None) -> list[float]:
    """Share of the residual sum of squares (after the base fit) each group explains on its own."""
    return fit_alone(y, groups, base)[0]


def fit_alone(
    y: torch.Tensor,  # [n] residual samples
    groups: list[torch.Tensor],  # each [n, k_g] basis columns of one candidate
    base: torch.Tensor | None = None,  # [n, q] columns always in the fit
) -> tuple[list[float], list[list[float]]]:
    """Each group fitted on its own (with the base columns): (the share of the residual sum of squares after the
    base fit it explains, its coefficients)."""
    base = _base_cols(base, y)
    _, total = lstsq(base, y)
    shares, coefs = [], []
    for x in groups:  # one small least-squares fit per candidate group, not per data element
        sol, rss = lstsq(torch.cat([base, x], dim=1), y)
        shares.append(1 - rss / total if total > 0 else 0.0)
        coefs.append([float(v) for v in sol[base.shape[1] :]])
    return shares, coefs


#: a column is estimated by a bootstrap resample only if the drawn trajectories hold more than this share of its
#: sum of squares (relative to the full data; a shared column holds about all of it in every resample)
ABSENT_SHARE = 0.1


def bootstrap(
    y: torch.Tensor,  # [B, m] residual samples grouped by trajectory
    groups: list[torch.Tensor],  # each [B, m, k_g]
    selected: list[int],
    n_boot: int = 100,
    seed: int = 0,
    max_terms: int = 6,
    base: torch.Tensor | None = None,  # [B, m, q] columns always in the fit
    same: list[int] | None = None,  # per group, a label: groups with one label are one effect written two ways
) -> tuple[dict[int, float], dict[int, list[tuple[float, float]]]]:
    """Resample trajectories with replacement; rerun the selection and refit the selected groups.

    A group's inclusion frequency counts the resamples that select it or a group with the same label in `same`
    (a drive with one phase per recording and the same drive with one shared phase: when the recordings' phases
    nearly agree, resamples choose between them, and either says the drive is there).

    Returns:
        ({group: inclusion frequency}, {selected group: [(2.5 %, 97.5 %) interval per coefficient]}).
    """
    b, m = y.shape[0], y.shape[1]
    gen = torch.Generator().manual_seed(seed)
    counts = [0] * len(groups)
    labels = list(range(len(groups))) if same is None else list(same)
    draws: dict[int, list[list[float]]] = {g: [] for g in selected}
    x, spans, base_cols = _design(list(groups), base)  # [B, m, P]
    grams = torch.einsum("bmp,bmq->bpq", x, x)  # per-trajectory normal equations: a resample is a weighted sum
    xtys = torch.einsum("bmp,bm->bp", x, y)
    ytys = y.pow(2).sum(dim=1)
    energy = grams.diagonal(dim1=1, dim2=2)  # [B, P] each column's sum of squares per trajectory
    total_energy = energy.mean(dim=0)  # [P] per trajectory on average
    chosen_cols = base_cols + [c for g in selected for c in spans[g]]
    for _ in range(n_boot):  # resamples, not a loop over data elements
        w = torch.bincount(torch.randint(0, b, (b,), generator=gen), minlength=b).to(x.dtype)  # multiplicities
        gram, xty, yty = torch.einsum("b,bpq->pq", w, grams), w @ xtys, float(w @ ytys)
        picked = {labels[g] for g in _stepwise_gram(gram, xty, yty, b * m, spans, base_cols, max_terms, same).groups}
        for g in range(len(groups)):
            counts[g] += labels[g] in picked
        if selected:
            sol, _ = _gram_fit(gram, xty, yty, chosen_cols)
            # a column whose data lie in recordings this resample did not draw (a recording's own drive phase;
            # after the nuisance projection a trace leaks into the others) is not estimated by it: NaN
            share = (w @ energy)[chosen_cols] / (b * total_energy[chosen_cols]).clamp(min=1e-300)
            sol = torch.where(share > ABSENT_SHARE, sol, torch.full_like(sol, math.nan))
            at = len(base_cols)
            for g in selected:
                k = len(spans[g])
                draws[g].append([float(v) for v in sol[at : at + k]])
                at += k
    freq = {g: counts[g] / n_boot for g in range(len(groups))}
    intervals = {}
    for g, rows in draws.items():
        values = torch.tensor(rows, dtype=torch.float64)
        lo = torch.nanquantile(values, 0.025, dim=0)
        hi = torch.nanquantile(values, 0.975, dim=0)
        intervals[g] = [(float(a), float(c)) for a, c in zip(lo, hi, strict=True)]
    return freq, intervals
