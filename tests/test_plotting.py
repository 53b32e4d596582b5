"""Plotting helpers."""

import pytest
from matplotlib.figure import Figure

from mpsim.plotting import at_least_a_factor


@pytest.mark.parametrize(("values", "span"), [((0.142, 0.148), 4.0), ((0.02, 0.4), None)])
def test_at_least_a_factor_widens_only_a_narrow_log_axis(values, span):
    # three errors 4 % apart must not fill the panel (autoscaled they read as a large effect); wider data keeps its
    # own autoscaled range
    ax = Figure().subplots()
    ax.plot([7, 13, 20], [values[0], values[1], values[0]], marker="o")
    ax.set(yscale="log")
    before = ax.get_ylim()
    at_least_a_factor(ax, 4.0)
    lo, hi = ax.get_ylim()
    assert lo < min(values) and max(values) < hi
    if span is None:
        assert (lo, hi) == before
    else:
        assert hi / lo == pytest.approx(span) and before[1] / before[0] < 1.2
