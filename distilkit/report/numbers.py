"""How the reports write a sweep's numbers: mean ± std over seeds, a signed difference, an interval.

One place, so that the table, the controls section and the scenes section of ``results.md`` write the same figure the
same way: a score shown in percent (``scale`` 100) with two decimals, any other to four significant digits.
"""

from __future__ import annotations

import math
import statistics


def mean_std(xs: list[float]) -> tuple[float, float]:
    """The mean and the sample standard deviation (NaN where a value is NaN, no value, or one value's std)."""
    if not xs or any(math.isnan(x) for x in xs):  # a score a stage does not have
        return math.nan, math.nan
    return statistics.fmean(xs), statistics.stdev(xs) if len(xs) > 1 else math.nan


def signed(d: float, scale: float) -> str:
    """A difference with its sign."""
    return f"{scale * d:+.2f}" if scale != 1.0 else f"{d:+.4g}"


def interval(low: float, high: float, scale: float) -> str:
    """``[low, high]`` with signs, or a dash where there is none (fewer than two seeds)."""
    return "—" if math.isnan(low) else f"[{signed(low, scale)}, {signed(high, scale)}]"


def pm(mean: float, std: float, scale: float = 100.0, sign: str = "") -> str:
    """``mean ± std`` (the mean alone where the std is NaN); ``sign="+"`` writes the mean's sign."""
    value = f"{scale * mean:{sign}.2f}" if scale != 1.0 else f"{mean:{sign}.4g}"
    if math.isnan(std):
        return value
    return f"{value} ± {scale * std:.2f}" if scale != 1.0 else f"{value} ± {std:.2g}"


__all__ = ["interval", "mean_std", "pm", "signed"]
