"""distilkit.report.numbers: the one way every section of results.md writes a figure."""

import math

from distilkit.report.numbers import interval, mean_std, pm, signed


def test_percent_scores_two_decimals_with_sign():
    assert signed(0.01234, 100.0) == "+1.23"
    assert signed(-0.5, 100.0) == "-50.00"
    assert interval(-0.01, 0.025, 100.0) == "[-1.00, +2.50]"
    assert pm(0.4131, 0.0084, 100.0) == "41.31 ± 0.84"
    assert pm(0.0248, 0.0084, 100.0, "+") == "+2.48 ± 0.84"


def test_other_scores_four_significant_digits():
    assert signed(0.123456, 1.0) == "+0.1235"
    assert interval(-2.0, 3.0, 1.0) == "[-2, +3]"
    assert pm(12.3456, 0.0123, 1.0) == "12.35 ± 0.012"


def test_missing_values_are_dashes_or_means_alone():
    assert interval(math.nan, math.nan, 100.0) == "—"
    assert pm(0.5, math.nan, 100.0) == "50.00"
    assert all(math.isnan(v) for v in mean_std([]))
    assert all(math.isnan(v) for v in mean_std([1.0, math.nan]))
    m, s = mean_std([1.0])
    assert m == 1.0 and math.isnan(s)
    m, s = mean_std([1.0, 2.0, 4.0])
    assert math.isclose(m, 7 / 3) and math.isclose(s, math.sqrt(((1 - 7 / 3) ** 2 + (2 - 7 / 3) ** 2 + (4 - 7 / 3) ** 2) / 2))
