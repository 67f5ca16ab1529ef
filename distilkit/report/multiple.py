"""Several distillation methods against one baseline over the same training seeds: multiple comparisons.

The design is paired: for method m and seed s, ``d[m, s] = score(m, s) − score(baseline, s)``. Here are the
family-wise corrections of the per-method p-values (Holm, Bonferroni), intervals that hold for all methods at once
(Bonferroni and max-t), the rank tests over all methods (Friedman with Iman–Davenport's F, Nemenyi's critical
difference and its diagram, after Demšar 2006, JMLR 7:1–30) and a two-stage bootstrap of a paired mIoU difference
that resamples the test scenes as well as the seeds. Pure functions on floats and numpy arrays (float64); scipy's
special functions for the tails (``scipy.stats`` only where a function needs it: its import costs half a second).
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import special


def _pvalues(pvalues: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(pvalues, dtype=np.float64).reshape(-1)
    ok = ~np.isnan(p)
    if np.any((p[ok] < 0) | (p[ok] > 1)):
        raise ValueError(f"p-values must lie in [0, 1]: {pvalues}")
    return p, ok


def holm(pvalues: Sequence[float]) -> list[float]:
    """Holm's step-down adjusted p-values (Holm 1979, Scand. J. Statist. 6:65–70): with the m non-NaN p-values
    sorted, p₍ᵢ₎ becomes max_{j≤i} min(1, (m − j + 1) p₍ⱼ₎). NaN stays NaN and does not count in m."""
    p, ok = _pvalues(pvalues)
    out = np.full(p.shape, np.nan)
    q = p[ok]
    order = np.argsort(q, kind="stable")
    adjusted = np.empty_like(q)
    adjusted[order] = np.minimum(1.0, np.maximum.accumulate((q.size - np.arange(q.size)) * q[order]))
    out[ok] = adjusted
    return out.tolist()


def bonferroni(pvalues: Sequence[float]) -> list[float]:
    """Bonferroni's adjusted p-values min(1, m p) over the m non-NaN p-values; NaN stays NaN."""
    p, ok = _pvalues(pvalues)
    return np.where(ok, np.minimum(1.0, ok.sum() * p), np.nan).tolist()


def _mean_sd(diffs: Sequence[float]) -> tuple[float, float, int]:
    d = np.asarray(diffs, dtype=np.float64).reshape(-1)
    if d.size < 2 or np.isnan(d).any():
        return math.nan, math.nan, d.size
    return float(d.mean()), float(d.std(ddof=1)), d.size


def paired_t_pvalue(diffs: Sequence[float]) -> float:
    """The two-sided p-value of the one-sample t test of mean 0 on the paired differences (Student 1908):
    t = d̄ / (s / √n) on n − 1 degrees of freedom. NaN for fewer than two values, a NaN value or no spread
    around a zero mean; 0 for no spread around a nonzero mean."""
    mean, sd, n = _mean_sd(diffs)
    if math.isnan(mean) or (sd == 0 and mean == 0):
        return math.nan
    if sd == 0:
        return 0.0
    return float(2.0 * special.stdtr(n - 1, -abs(mean) / (sd / math.sqrt(n))))


def t_quantile(p: float, df: int) -> float:
    """Student's t quantile (``scipy.special.stdtrit``: the value of ``scipy.stats.t.ppf``, without importing
    scipy.stats — half a second in every process that writes a table)."""
    return float(special.stdtrit(df, p))


_t_quantile = t_quantile


def t_interval(xs: Sequence[float], level: float = 0.95) -> tuple[float, float]:
    """The two-sided ``level`` Student-t interval of the mean of ``xs`` (nan for fewer than two values or a NaN)."""
    if len(xs) < 2 or any(math.isnan(x) for x in xs):
        return math.nan, math.nan
    mean, sd = statistics.fmean(xs), statistics.stdev(xs)
    half = t_quantile(0.5 + level / 2, len(xs) - 1) * sd / math.sqrt(len(xs))
    return mean - half, mean + half


def max_t_critical(corr: np.ndarray, n: int, level: float = 0.95, draws: int = 200_000, seed: int = 0) -> float:
    """The ``level`` quantile of max_j |T_j|, T_j = x̄_j / (s_j / √n), for n rows drawn from N(0, ``corr``): the
    exact null distribution of the paired t statistics of correlated normal differences, each with its own s_j
    (each T_j is scale-free: the correlation fixes their joint law), by Monte Carlo. The draws are standard normals
    from ``np.random.default_rng(seed)``, taken in chunks of at most 2²² numbers, each of shape (chunk, n, m) and
    mapped by the symmetric root of ``corr``."""
    w, v = np.linalg.eigh(np.asarray(corr, dtype=np.float64))
    root = (v * np.sqrt(np.clip(w, 0.0, None))) @ v.T  # a singular corr (perfectly correlated methods) is fine
    rng, m = np.random.default_rng(seed), root.shape[0]
    chunk, maxima = max(1, (1 << 22) // (n * m)), []
    for start in range(0, draws, chunk):
        x = rng.standard_normal((min(chunk, draws - start), n, m)) @ root
        maxima.append(np.abs(x.mean(axis=1) / (x.std(axis=1, ddof=1) / math.sqrt(n))).max(axis=1))
    return float(np.quantile(np.concatenate(maxima), level))


def simultaneous_intervals(diffs_by_method: Mapping[str, Sequence[float]], level: float = 0.95,
                           method: str = "bonferroni", draws: int = 200_000,
                           seed: int = 0) -> dict[str, tuple[float, float]]:
    """Intervals for the mean paired difference of every method that cover all true means together with
    probability ``level``: d̄ ± c · s / √n.

    ``bonferroni``: c = t_{1 − α/(2m), n−1}, each method's t interval at level 1 − α/m (Dunn 1961,
    JASA 56:52–64). ``max-t``: c = the ``level`` quantile of max_j |T_j| over the m methods (Hothorn, Bretz &
    Westfall 2008, Biom. J. 50:346–363): the methods share the seeds, so their t statistics are correlated; c is
    computed by :func:`max_t_critical` with the sample correlation of the paired differences (n seeds × m methods),
    simulating whole samples so that each T_j keeps its own s_j (the multivariate t, with one shared χ², would be
    exact only for a pooled variance). It needs the same seeds for every method. Methods with fewer than two
    values or a NaN get (nan, nan) and are left out of m; one without spread gets (d̄, d̄) and is left out of the
    correlation."""
    if not 0 < level < 1 or method not in ("bonferroni", "max-t"):
        raise ValueError(f"level in (0, 1) and method 'bonferroni' or 'max-t', not {level!r}, {method!r}")
    summary = {name: _mean_sd(d) for name, d in diffs_by_method.items()}
    valid = [name for name, (mean, _, _) in summary.items() if not math.isnan(mean)]
    out = {name: (math.nan, math.nan) for name in summary}
    if not valid:
        return out
    if method == "bonferroni":
        crit = {name: _t_quantile(1 - (1 - level) / (2 * len(valid)), summary[name][2] - 1) for name in valid}
    else:
        if len({summary[name][2] for name in valid}) > 1:
            raise ValueError("max-t needs every method over the same seeds")
        spread = [name for name in valid if summary[name][1] > 0]
        crit = dict.fromkeys(valid, 0.0)
        if spread:
            d = np.array([np.asarray(diffs_by_method[name], dtype=np.float64).reshape(-1) for name in spread]).T
            corr = np.corrcoef(d, rowvar=False).reshape(len(spread), len(spread))
            crit.update(dict.fromkeys(spread, max_t_critical(corr, d.shape[0], level, draws, seed)))
    for name in valid:
        mean, sd, n = summary[name]
        half = crit[name] * sd / math.sqrt(n)
        out[name] = (mean - half, mean + half)
    return out


@dataclass(frozen=True)
class FriedmanResult:
    """Average ranks (rank 1 = best) of the k methods over the n blocks, Friedman's χ² with its p-value and
    Iman–Davenport's F with its p-value."""

    ranks: np.ndarray
    chi2: float
    p_chi2: float
    f: float
    p_f: float
    n: int
    k: int


def friedman(scores: np.ndarray, tie_correction: bool = False) -> FriedmanResult:
    """Friedman's test on ``scores`` of shape (n blocks — the seeds, k methods incl. the baseline), higher is
    better (Demšar 2006, JMLR 7:1–30, section 3.2.2). Ranks within each block, ties averaged; R_j = average rank;
    χ²_F = 12n / (k(k+1)) · (Σ R_j² − k(k+1)²/4) on k − 1 degrees of freedom, and Iman & Davenport's
    F_F = (n − 1) χ²_F / (n(k − 1) − χ²_F) on (k − 1, (k − 1)(n − 1)) degrees of freedom (1980, Comm.
    Statist. A 9:571–595). ``tie_correction`` divides χ²_F by 1 − Σ(t³ − t) / (n k (k² − 1)) over the groups
    of t tied scores in a block (Hollander & Wolfe 1999, Nonparametric Statistical Methods, chapter 7; what
    ``scipy.stats.friedmanchisquare`` reports); Demšar's formulas have none."""
    from scipy.stats import rankdata

    x = np.asarray(scores, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] < 2 or x.shape[1] < 2 or np.isnan(x).any():
        raise ValueError(f"scores: (blocks ≥ 2, methods ≥ 2) without NaN, not shape {x.shape}")
    n, k = x.shape
    r = rankdata(-x, axis=1)  # rank 1 = the highest score
    ranks = r.mean(axis=0)
    chi2 = 12.0 * n / (k * (k + 1)) * (float(np.sum(ranks**2)) - k * (k + 1) ** 2 / 4.0)
    if tie_correction:
        ties = sum(float(np.sum(c**3 - c)) for c in (np.unique(row, return_counts=True)[1] for row in x))
        c = 1.0 - ties / (n * k * (k * k - 1))
        chi2 = chi2 / c if c > 0 else math.nan
    chi2 = max(chi2, 0.0)  # not -1e-15 where every block ties (NaN stays NaN)
    room = n * (k - 1) - chi2  # 0 where every block ranks alike: F_F = ∞
    f, p_f = (math.nan, math.nan) if math.isnan(chi2) else (math.inf, 0.0)
    if room > 0:
        f = (n - 1) * chi2 / room
        p_f = float(special.fdtrc(k - 1, (k - 1) * (n - 1), f))
    return FriedmanResult(ranks, chi2, float(special.chdtrc(k - 1, chi2)), f, p_f, n, k)


def nemenyi_cd(k: int, n: int, alpha: float = 0.05) -> float:
    """Nemenyi's critical difference of average ranks, CD = q_α √(k(k+1) / (6n)) with q_α the studentized range
    quantile on (k, ∞) degrees of freedom divided by √2 (Demšar 2006, section 3.2.2 and Table 5a)."""
    from scipy.stats import studentized_range

    q = float(studentized_range.ppf(1 - alpha, k, np.inf)) / math.sqrt(2)
    return q * math.sqrt(k * (k + 1) / (6.0 * n))


def cd_groups(ranks: Mapping[str, float], cd: float) -> list[tuple[str, ...]]:
    """The bars of a critical-difference diagram (Demšar 2006, Figure 1): the maximal groups of at least two methods
    whose average ranks all differ by less than ``cd``, best first, each in rank order (ties by name). On a line
    these maximal cliques are runs of consecutive methods; a method apart from all others is in none."""
    names = sorted(ranks, key=lambda name: (ranks[name], name))
    groups: list[tuple[str, ...]] = []
    last = 0
    for i, first in enumerate(names):
        j = i
        while j + 1 < len(names) and ranks[names[j + 1]] - ranks[first] < cd:
            j += 1
        if j > i and j + 1 > last:  # not inside the previous run
            groups.append(tuple(names[i:j + 1]))
            last = j + 1
    return groups


def plot_cd(ranks: Mapping[str, float], cd: float, path: Path | str, title: str | None = None) -> Path:
    """Draw the critical-difference diagram (Demšar 2006, Figure 1) to a PNG: the rank axis 1..k (best on the left),
    each method's name joined to its average rank (the better half on the left, the rest on the right), a thick
    bar under each group of :func:`cd_groups` and the CD's length above the axis."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    path = Path(path)
    names = sorted(ranks, key=lambda name: (ranks[name], name))
    k, groups = len(names), cd_groups(ranks, cd)
    half = (k + 1) // 2
    rows = max(half, k - half) + len(groups)
    fig = Figure(figsize=(7.0, 1.4 + 0.28 * rows))
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.2, 0.02, 0.6, 0.8 if title else 0.9))
    ax.set_axis_off()
    top = max(k, 2)
    ax.set_xlim(1, top)
    ax.set_ylim(-(rows + 1) * 0.3, 0.6)
    ax.plot([1, top], [0, 0], color="black", linewidth=1)
    for tick in range(1, top + 1):
        ax.plot([tick, tick], [0, 0.08], color="black", linewidth=1)
        ax.text(tick, 0.12, str(tick), ha="center", va="bottom", fontsize=9)
    ax.plot([1, 1 + cd], [0.45, 0.45], color="black", linewidth=1.5)
    ax.text(1 + cd / 2, 0.48, f"CD = {cd:.2f}", ha="center", va="bottom", fontsize=8)
    for i, name in enumerate(names):
        left = i < half
        y = -0.3 * (len(groups) + 1 + (i if left else k - 1 - i))
        end = 1 - 0.05 * top if left else top + 0.05 * top
        ax.plot([ranks[name], ranks[name], end], [0, y, y], color="black", linewidth=0.8, clip_on=False)
        ax.text(end, y, f"{name} ({ranks[name]:.2f})" if left else f"({ranks[name]:.2f}) {name}", fontsize=9,
                ha="right" if left else "left", va="center")
    for g, group in enumerate(groups):
        y = -0.3 * (g + 0.6)
        ax.plot([ranks[group[0]] - 0.03, ranks[group[-1]] + 0.03], [y, y], color="black", linewidth=3)
    if title:
        fig.suptitle(title, fontsize=10)
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=110, bbox_inches="tight", pad_inches=0.15)  # the names whole, however long
    tmp.replace(path)  # never half a PNG
    return path


def _miou(counts: np.ndarray, absent: str = "skip") -> np.ndarray:
    """mIoU over the last axis of (inter, union) stacked on axis 0: the mean over the classes with union > 0
    (``absent="skip"``), or over every class, one with union 0 scoring 0 (``"zero"``: SemanticKITTI's
    ``evaluate_completion.py``, :func:`distilkit.metrics.ssc.ssc_scores`)."""
    inter, union = counts
    seen = union > 0
    iou = np.divide(inter, union, out=np.zeros_like(inter), where=seen)
    if absent == "zero":
        return iou.mean(axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return iou.sum(axis=-1) / seen.sum(axis=-1)


def hierarchical_bootstrap(inter: Mapping[str, np.ndarray], union: Mapping[str, np.ndarray], method: str,
                           baseline: str, draws: int = 2000, level: float = 0.95,
                           seed: int = 0, absent: str = "skip") -> tuple[float, float, float]:
    """The paired mIoU difference of ``method`` to ``baseline`` with a percentile bootstrap interval that resamples
    the training seeds and the test scenes, both with replacement. Every seed is scored on the same test scenes, so
    seeds and scenes are crossed, not nested: one draw of the scenes serves every seed of a replicate (Owen 2007,
    "The pigeonhole bootstrap", Ann. Appl. Stat. 1:386–411). Scenes drawn afresh for each seed would treat their
    noise as independent between seeds and divide it by the number of seeds. ``inter[m]``, ``union[m]``:
    intersection and union counts of shape (seeds S, scenes J, classes C), both models over the same seeds and
    scenes; mIoU sums the counts over the scenes and averages inter/union over the classes with union > 0
    (``absent="zero"``: over every class, one with union 0 scoring 0, as the official SSC mIoU: see :func:`_miou`).

    Returns (estimate, lower, upper): the estimate is the mean over the seeds of the per-seed mIoU differences on
    the data as given; the interval is the (1 ± ``level``)/2 quantiles (numpy's linear ones) of ``draws``
    replicates. Order of the random draws, all from ``np.random.default_rng(seed)``: first
    ``integers(0, S, size=(draws, S))``, the seeds of every replicate; then ``integers(0, J, size=(draws, J))``, the
    scenes of replicate b (the same for its every seed, the method and the baseline). A replicate is the mean over
    its S drawn seeds of their mIoU differences on its drawn scenes.

    The seeds-only t interval takes each seed's score on the fixed test set as exact, so it speaks of training noise
    alone; resampling the scenes adds the test set's own sampling noise (which scenes happened to be in it), so
    where the method's gain varies from scene to scene this interval is wider and speaks of new scenes as well."""
    arrays = [np.asarray(a[name], dtype=np.float64) for a in (inter, union) for name in (method, baseline)]
    shape = arrays[0].shape
    if len(shape) != 3 or any(a.shape != shape for a in arrays) or not 0 < level < 1:
        raise ValueError("inter and union: (seeds, scenes, classes), one shape for both models; level in (0, 1)")
    n_seeds, n_scenes, n_classes = shape
    stacked = np.concatenate(arrays, axis=-1)  # (S, J, 4C): inter m, inter b, union m, union b
    if absent not in ("skip", "zero"):
        raise ValueError(f"absent: 'skip' or 'zero', got {absent!r}")
    estimate = float(np.mean(_diff(stacked.sum(axis=1), n_classes, absent)))
    rng = np.random.default_rng(seed)
    seeds = rng.integers(0, n_seeds, size=(draws, n_seeds))
    scenes = rng.integers(0, n_scenes, size=(draws, n_scenes))
    rows = np.arange(draws)[:, None] * n_scenes
    times = np.bincount((rows + scenes).ravel(), minlength=draws * n_scenes).reshape(draws, n_scenes)
    per_seed = np.einsum("bj,sjc->bsc", times.astype(np.float64), stacked)  # each seed's counts on b's scenes
    counts = np.take_along_axis(per_seed, seeds[:, :, None], axis=1)  # (draws, S, 4C): the drawn seeds'
    replicates = _diff(counts, n_classes, absent).mean(axis=1)
    low, high = np.quantile(replicates, [(1 - level) / 2, (1 + level) / 2])
    return estimate, float(low), float(high)


def _diff(counts: np.ndarray, c: int, absent: str = "skip") -> np.ndarray:
    """mIoU(method) − mIoU(baseline) from counts whose last axis is (inter m, inter b, union m, union b) × C."""
    inter = counts[..., :2 * c].reshape(*counts.shape[:-1], 2, c)
    union = counts[..., 2 * c:].reshape(*counts.shape[:-1], 2, c)
    miou = _miou(np.stack([inter, union]), absent)
    return miou[..., 0] - miou[..., 1]


__all__ = ["FriedmanResult", "bonferroni", "cd_groups", "friedman", "hierarchical_bootstrap", "holm", "max_t_critical", "nemenyi_cd", "paired_t_pvalue", "plot_cd", "simultaneous_intervals", "t_interval", "t_quantile"]
