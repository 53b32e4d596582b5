import pytest
import torch

from mpsim.diagnose.select import bootstrap, explained_alone, project_out, stepwise_bic


def _data(n=2000, seed=0):
    g = torch.Generator().manual_seed(seed)
    cols = [torch.randn(n, 1, generator=g, dtype=torch.float64) for _ in range(5)]
    forcing = torch.randn(n, 2, generator=g, dtype=torch.float64)
    y = (
        0.8 * cols[1][:, 0]
        - 0.5 * forcing[:, 0]
        + 0.3 * forcing[:, 1]
        + 0.05 * torch.randn(n, generator=g, dtype=torch.float64)
    )
    return y, [*cols, forcing]


def test_stepwise_picks_the_true_groups_with_their_coefficients():
    y, groups = _data()
    sel = stepwise_bic(y, groups)
    assert sorted(sel.groups) == [1, 5]
    assert abs(sel.coef[1][0] - 0.8) < 0.01 and abs(sel.coef[5][0] + 0.5) < 0.01 and abs(sel.coef[5][1] - 0.3) < 0.01
    assert sel.r2 > 0.99


def test_pure_noise_selects_little_and_explains_little():
    g = torch.Generator().manual_seed(1)
    y = torch.randn(2000, generator=g, dtype=torch.float64)
    groups = [torch.randn(2000, 1, generator=g, dtype=torch.float64) for _ in range(6)]
    sel = stepwise_bic(y, groups)
    assert sel.r2 < 0.01
    assert max(explained_alone(y, groups)) < 0.01


def test_base_columns_are_refit_not_named():
    # the residual contains a model-parameter error (base column) plus a damping-like term
    y, groups = _data()
    base = groups[0]
    y = y + 2.0 * base[:, 0]
    sel = stepwise_bic(y, groups[1:], base=base)
    assert sorted(sel.groups) == [0, 4]  # indices into groups[1:]: the true terms only


def test_bootstrap_intervals_cover_the_truth():
    y, groups = _data(n=4000)
    b = 40
    freq, ci = bootstrap(y.reshape(b, -1), [g.reshape(b, -1, g.shape[1]) for g in groups], [1, 5], n_boot=40)
    assert freq[1] == 1.0 and freq[5] == 1.0 and freq[0] < 0.5
    ((lo, hi),) = ci[1]
    assert lo < 0.8 < hi


def test_a_recordings_own_columns_are_estimated_only_by_resamples_that_draw_it():
    # a drive with its own phase in every recording: two columns per recording, zero in the others until the
    # nuisance projection leaks a trace of them everywhere; a resample that does not draw recording b says
    # nothing about b's coefficients (before: the solver's zero or a wild value entered the interval)
    gen = torch.Generator().manual_seed(0)
    b, n_t = 40, 99
    t = torch.linspace(0, 5, n_t, dtype=torch.float64)
    cols = torch.zeros(b, n_t, 2 * b, dtype=torch.float64)
    idx = torch.arange(b)
    cols[idx, :, 2 * idx] = torch.sin(20 * t)
    cols[idx, :, 2 * idx + 1] = torch.cos(20 * t)
    phase = torch.rand(b, generator=gen, dtype=torch.float64) * 6.28
    y = 12 * torch.sin(20 * t[None] + phase[:, None]) + torch.randn(b, n_t, generator=gen, dtype=torch.float64)
    base = torch.randn(b * n_t, 5, generator=gen, dtype=torch.float64)
    y_p, cols_p = project_out(base, y.reshape(-1), cols.reshape(b * n_t, -1))
    freq, intervals = bootstrap(y_p.reshape(b, n_t), [cols_p.reshape(b, n_t, -1)], [0], n_boot=60)
    assert freq[0] == 1.0
    truth = torch.stack([12 * torch.cos(phase), 12 * torch.sin(phase)], dim=1).reshape(-1)  # [2B] (a, b) pairs
    width = torch.tensor([hi - lo for lo, hi in intervals[0]])
    lo = torch.tensor([lo for lo, _ in intervals[0]])
    assert bool((width < 1.0).all())  # each from the resamples that drew its recording: ± a few noise units
    assert bool(((truth - lo).abs() < 1.0).all())


def test_one_effect_written_two_ways_counts_once_in_the_inclusion_frequency():
    # two versions of one term (say a drive with a phase per recording and with one shared phase): resamples
    # pick one or the other, so each alone is selected in only part of them; labelled as one effect, either counts
    gen = torch.Generator().manual_seed(1)
    b, m = 30, 50
    term = torch.randn(b, m, 1, generator=gen, dtype=torch.float64)
    twin = term + 0.05 * torch.randn(b, m, 1, generator=gen, dtype=torch.float64)
    y = (term + twin)[..., 0] + torch.randn(b, m, generator=gen, dtype=torch.float64)
    apart, _ = bootstrap(y, [term, twin], [0], n_boot=60)
    together, _ = bootstrap(y, [term, twin], [0], n_boot=60, same=[0, 0])
    assert min(apart.values()) < 0.8  # each alone looks unstable
    assert together == {0: 1.0, 1: 1.0}


def test_a_wide_group_that_lowers_the_residual_most_does_not_stop_the_selection():
    """Each step adds the group that lowers the BIC most: a 40-column group (a drive with a phase per recording)
    fits a little more of the residual than the one-column truth but pays 40·log(n); the truth is chosen, not
    the selection stopped."""
    gen = torch.Generator().manual_seed(0)
    n = 400
    truth = torch.randn(n, 1, generator=gen, dtype=torch.float64)
    y = 0.5 * truth[:, 0] + 0.1 * torch.randn(n, generator=gen, dtype=torch.float64)
    wide = torch.cat([truth, torch.randn(n, 39, generator=gen, dtype=torch.float64)], dim=1)  # holds the truth too
    sel = stepwise_bic(y, [wide, truth])
    assert sel.groups == [1]
    assert sel.coef[1][0] == pytest.approx(0.5, abs=0.03)


def test_one_effect_written_two_ways_is_selected_once():
    """A drive with a phase per recording at ω₁ and the shared-phase drive at ω₂ ≈ ω₁ are nearly collinear; on a
    drive a little off both frequencies the pair together fits better than either, so without the labels the
    selection takes both with coefficients that cancel each other (case 2: 77 and −67 for a true 10).
    Labelled as one effect, only one of them is chosen, with a coefficient near the truth."""
    b, m = 20, 100
    t = torch.linspace(0, 5, m, dtype=torch.float64)
    gen = torch.Generator().manual_seed(0)

    def waves(omega):  # [m, 2]
        return torch.stack([torch.sin(omega * t), torch.cos(omega * t)], dim=-1)

    shared = waves(20.015)[None].expand(b, m, 2)
    phased = torch.zeros(b, m, 2 * b, dtype=torch.float64)
    for r in range(b):  # a test fixture of 20 recordings
        phased[r, :, 2 * r : 2 * r + 2] = waves(20.02)
    y = 10 * torch.sin(20.0 * t)[None].expand(b, m) + 0.2 * torch.randn(b, m, generator=gen, dtype=torch.float64)
    groups = [shared.reshape(b * m, 2), phased.reshape(b * m, 2 * b)]
    both = stepwise_bic(y.reshape(-1), groups)
    assert sorted(both.groups) == [0, 1]  # unlabelled: both chosen, and they cancel
    assert max(abs(v) for v in both.coef[0]) > 30
    one = stepwise_bic(y.reshape(-1), groups, same=[0, 0])
    assert len(one.groups) == 1
    g = one.groups[0]
    assert max(abs(v) for v in one.coef[g]) == pytest.approx(10, rel=0.1)
