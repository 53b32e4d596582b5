import torch

from mpsim.diagnose.select import bootstrap, explained_alone, stepwise_bic


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
