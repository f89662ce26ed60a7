"""The Wilson interval every success table in docs/ is reported with."""

from zetta_wire.stats import wilson


def test_interval_of_known_values() -> None:
    """8/10 gives the textbook 49.0%-94.3%."""
    lo, hi = wilson(8, 10)
    assert 0.49 < lo < 0.50 and 0.94 < hi < 0.95


def test_extremes_stay_inside_zero_one() -> None:
    """All-success and all-failure runs keep a non-degenerate interval within [0, 1]."""
    assert wilson(16, 16)[0] > 0.79 and wilson(16, 16)[1] == 1.0
    assert wilson(0, 50) == (0.0, wilson(0, 50)[1]) and 0.07 < wilson(0, 50)[1] < 0.08


def test_no_trials_rules_nothing_out() -> None:
    """With no episodes the interval is the whole range."""
    assert wilson(0, 0) == (0.0, 1.0)
