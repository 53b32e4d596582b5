"""The held-out acceptance test's statistics (`mpsim.diagnose.stats`): the paired gain and log error ratio over
recordings and the bar they must clear."""

import math

import pytest
import torch

from mpsim.diagnose.stats import critical, log_ratio, paired


def test_the_bar_is_students_t_at_the_gaussian_level_of_the_margin():
    """Textbook two-sided 95 % t values (t_{0.975}): 12.706 (1 d.o.f.), 2.571 (5), 2.228 (10); z = 1.95996."""
    z = 1.959964
    assert critical(z, 2) == pytest.approx(12.706, abs=1e-3)
    assert critical(z, 6) == pytest.approx(2.571, abs=1e-3)
    assert critical(z, 11) == pytest.approx(2.228, abs=1e-3)
    assert critical(z, 10_000) == pytest.approx(z, abs=1e-3)  # many recordings: the Gaussian bar
    assert critical(2.0, 1) == math.inf and critical(2.0, 0) == math.inf  # one recording has no standard error


def test_log_ratio_counts_only_the_recordings_where_it_is_finite():
    before = torch.tensor([1.0, 1.0, float("inf"), 4.0], dtype=torch.float64)  # [B]
    after = torch.tensor([0.5, 0.25, 1.0, 1.0], dtype=torch.float64)  # [B]
    mean, se, n = log_ratio(before, after, 0.0)
    logs = torch.log(torch.tensor([2.0, 4.0, 4.0], dtype=torch.float64))
    assert n == 3
    assert mean == pytest.approx(float(logs.mean()))
    assert se == pytest.approx(float(logs.std() / math.sqrt(3)))
    assert log_ratio(before[2:3], after[2:3], 0.0) == (-math.inf, math.inf, 0)


def test_paired_gain_counts_only_the_finite_differences_and_carries_the_log_ratio_and_its_bar():
    before = torch.tensor([1.0, 2.0, float("inf"), 4.0], dtype=torch.float64)  # [B]
    after = torch.tensor([0.5, 1.0, 1.0, 1.0], dtype=torch.float64)  # [B]
    p = paired(before, after, 0.0, 2.0)
    diffs = torch.tensor([0.5, 1.0, 3.0], dtype=torch.float64)
    assert p.gain == pytest.approx(float(diffs.mean()))
    assert p.gain_se == pytest.approx(float(diffs.std() / math.sqrt(3)))
    assert (p.log_ratio, p.log_ratio_se, p.n) == log_ratio(before, after, 0.0)
    assert p.bar == critical(2.0, 3)
    one = paired(before[:1], after[:1], 0.0, 2.0)  # one recording: no standard error, an infinite bar
    assert one.gain == pytest.approx(0.5) and one.gain_se == math.inf and one.bar == math.inf
    none = paired(before[2:3], before[2:3], 0.0, 2.0)  # inf - inf: nothing finite to compare
    assert none.gain == -math.inf and none.n == 0


def test_hac_mean_counts_independent_windows_as_samples_and_identical_ones_as_one_record():
    from mpsim.diagnose.stats import hac_mean

    gen = torch.Generator().manual_seed(0)
    iid = torch.randn(4, 200, generator=gen, dtype=torch.float64)
    mean, se, n_eff = hac_mean(iid)
    assert mean == pytest.approx(float(iid.mean()))
    assert se == pytest.approx(float(iid.std() / math.sqrt(iid.numel())), rel=0.15)
    assert n_eff > 500  # of 800 windows: nearly every one counts
    # every window of a record alike: the windows carry no more evidence than the records
    same = torch.tensor([[1.0], [2.0], [0.5], [1.5]], dtype=torch.float64).expand(4, 6)
    _, se_same, n_same = hac_mean(same)
    assert n_same == 4 and se_same == pytest.approx(float(same[:, 0].std() / 2))  # the records' own test
    # a record with a non-finite window is left out whole
    bad = iid[:, :5].clone()
    bad[0, 2] = math.inf
    assert hac_mean(bad)[0] == pytest.approx(float(iid[1:, :5].mean()))


def test_paired_on_windows_says_what_it_counted():
    before = torch.full((3, 4), 2.0, dtype=torch.float64) + 0.1 * torch.arange(12.0, dtype=torch.float64).reshape(3, 4)
    after = before / 4
    p = paired(before, after, 1e-12, 2.0)
    assert p.log_ratio == pytest.approx(math.log(4))
    assert "held-out windows in 3 recordings" in p.over and p.n >= 3
    assert paired(before[:, 0], after[:, 0], 1e-12, 2.0).over == "3 held-out recordings"
