"""Multiple comparisons of several methods to one baseline over shared seeds (distilkit/report/multiple.py)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy import stats
from statsmodels.stats.multitest import multipletests

from distilkit.report.multiple import (bonferroni, cd_groups, friedman, hierarchical_bootstrap, holm, max_t_critical,
                                       nemenyi_cd, paired_t_pvalue, plot_cd, simultaneous_intervals)

# Demšar 2006 (JMLR 7:1–30), Table 6: AUC of C4.5, C4.5+m, C4.5+cf and C4.5+m+cf on 14 UCI data sets, as printed.
# The paper ranks voting's C4.5+cf (0.975) 2nd and C4.5+m+cf (0.975) 3rd, from unrounded values: 0.9751 keeps that.
DEMSAR_METHODS = ("C4.5", "C4.5+m", "C4.5+cf", "C4.5+m+cf")
DEMSAR_AUC = np.array([
    [0.763, 0.768, 0.771, 0.798], [0.599, 0.591, 0.590, 0.569], [0.954, 0.971, 0.968, 0.967],
    [0.628, 0.661, 0.654, 0.657], [0.882, 0.888, 0.886, 0.898], [0.936, 0.931, 0.916, 0.931],
    [0.661, 0.668, 0.609, 0.685], [0.583, 0.583, 0.563, 0.625], [0.775, 0.838, 0.866, 0.875],
    [1.000, 1.000, 1.000, 1.000], [0.940, 0.962, 0.965, 0.962], [0.619, 0.666, 0.614, 0.669],
    [0.972, 0.981, 0.9751, 0.975], [0.957, 0.978, 0.946, 0.970]])
DEMSAR_RANKS = dict(zip(DEMSAR_METHODS, (3.143, 2.000, 2.893, 1.964)))
# Demšar 2006, Table 5(a): q_α of the two-tailed Nemenyi test for k = 2..10 methods
DEMSAR_Q = {0.05: (1.960, 2.343, 2.569, 2.728, 2.850, 2.949, 3.031, 3.102, 3.164),
            0.10: (1.645, 2.052, 2.291, 2.459, 2.589, 2.693, 2.780, 2.855, 2.920)}


def _with_nan(adjusted: np.ndarray, where: list[int], size: int) -> list[float]:
    out = [math.nan] * size
    for i, v in zip(where, adjusted):
        out[i] = float(v)
    return out


@pytest.mark.parametrize("ours, theirs", [(holm, "holm"), (bonferroni, "bonferroni")])
def test_adjusted_pvalues_match_statsmodels(ours, theirs) -> None:
    rng = np.random.default_rng(0)
    cases = [rng.uniform(0, 1, size) * rng.choice([1e-3, 0.1, 1.0]) for size in (1, 2, 3, 5, 8, 13) for _ in range(5)]
    cases += [[0.01, 0.01, 0.04, 0.5], [0.02, 0.02, 0.02], [0.6, 0.7, 0.9], [0.0, 1.0, 0.5], [0.01, 0.04, 0.03]]
    for p in cases:
        assert ours(p) == pytest.approx(multipletests(p, method=theirs)[1], rel=1e-12, abs=0)
    p = [0.02, math.nan, 0.01, 0.03, math.nan]  # NaN: passed through and not counted in the family
    kept = [0, 2, 3]
    expected = _with_nan(multipletests([p[i] for i in kept], method=theirs)[1], kept, len(p))
    assert ours(p) == pytest.approx(expected, nan_ok=True)
    assert ours([math.nan, math.nan]) == pytest.approx([math.nan, math.nan], nan_ok=True) and ours([]) == []
    with pytest.raises(ValueError):
        ours([0.5, 1.5])


def test_holm_by_hand() -> None:
    # sorted .01, .03, .04 → 3·.01, 2·.03, 1·.04 = .03, .06, .04 → monotone: .03, .06, .06
    assert holm([0.01, 0.04, 0.03]) == pytest.approx([0.03, 0.06, 0.06])
    assert holm([0.6, 0.7]) == [1.0, 1.0]  # capped at 1 and monotone
    assert holm([0.01, math.nan, 0.01]) == pytest.approx([0.02, math.nan, 0.02], nan_ok=True)  # ties: one value


def test_paired_t_pvalue_matches_scipy() -> None:
    rng = np.random.default_rng(1)
    for n in (2, 3, 5, 10, 30):
        for shift in (0.0, 0.3, 2.0):
            d = rng.normal(shift, 1.0, n)
            assert paired_t_pvalue(d) == pytest.approx(stats.ttest_1samp(d, 0.0).pvalue, rel=1e-10)
    assert math.isnan(paired_t_pvalue([0.4]))  # fewer than two
    assert math.isnan(paired_t_pvalue([0.0, 0.0, 0.0]))  # no spread around 0
    assert math.isnan(paired_t_pvalue([0.1, math.nan, 0.2]))
    assert paired_t_pvalue([0.5, 0.5, 0.5]) == 0.0  # no spread around a nonzero mean


def test_bonferroni_intervals_by_hand() -> None:
    diffs = {"kd": [0.01, 0.03, 0.02, 0.05, 0.00], "dskd": [0.02, 0.02, 0.04, 0.01, 0.03],
             "fitnet": [-0.01, 0.02, 0.00, 0.01, -0.02], "broken": [0.01, math.nan, 0.02, 0.0, 0.0]}
    got = simultaneous_intervals(diffs, 0.95, "bonferroni")
    q = stats.t.ppf(1 - 0.05 / (2 * 3), 4)  # three methods with an interval: α/m = 0.05/3 each
    for name in ("kd", "dskd", "fitnet"):
        d = np.array(diffs[name])
        half = q * d.std(ddof=1) / math.sqrt(5)
        assert got[name] == pytest.approx((d.mean() - half, d.mean() + half), rel=1e-12)
    assert all(math.isnan(v) for v in got["broken"])


def _like_t_interval(got: tuple[float, float], d: np.ndarray, rel: float) -> None:
    """``got`` is the 95 % t interval of ``d``: the same centre, the half-width to ``rel``."""
    half = stats.t.ppf(0.975, len(d) - 1) * d.std(ddof=1) / math.sqrt(len(d))
    assert (got[0] + got[1]) / 2 == pytest.approx(d.mean(), rel=1e-12)
    assert (got[1] - got[0]) / 2 == pytest.approx(half, rel=rel)


def test_max_t_with_one_method_is_the_t_interval() -> None:
    d = np.random.default_rng(2).normal(0.02, 0.01, 6)
    # Monte Carlo error of the 0.95 quantile of |t₅| from 200 000 draws: about 0.3 % (sd 0.008 on 2.571)
    _like_t_interval(simultaneous_intervals({"kd": d}, method="max-t")["kd"], d, rel=0.01)


def test_max_t_with_perfectly_correlated_methods_is_each_t_interval() -> None:
    a = np.random.default_rng(3).normal(0.02, 0.01, 6)
    diffs = {"a": a, "twice": 2 * a + 0.01, "mirror": -a}  # correlations 1, 1 and −1: one |T| for all
    got = simultaneous_intervals(diffs, method="max-t")
    for name, d in diffs.items():
        _like_t_interval(got[name], d, rel=0.01)


def test_max_t_with_independent_methods_is_sidak_between_t_and_bonferroni() -> None:
    # the columns of a Hadamard matrix of order 8 but its constant one: centred, orthogonal, sample correlation 0
    h = np.array([[1]])
    for _ in range(3):
        h = np.block([[h, h], [h, -h]])
    d = 0.01 * h[:, 1:5] + np.array([0.01, 0.02, 0.0, -0.01])
    assert np.corrcoef(d, rowvar=False) == pytest.approx(np.eye(4), abs=1e-12)
    crit = max_t_critical(np.eye(4), 8, 0.95, draws=400_000)
    sidak = stats.t.ppf(0.5 + 0.95 ** 0.25 / 2, 7)  # independent: P(max |T| ≤ c) = P(|T| ≤ c)⁴
    per_method, bonf = stats.t.ppf(0.975, 7), stats.t.ppf(1 - 0.05 / 8, 7)
    assert crit == pytest.approx(sidak, abs=0.03)  # Monte Carlo sd about 0.008
    assert per_method + 0.5 < crit < bonf + 0.03  # Šidák lies 0.014 under Bonferroni: within the Monte Carlo error
    got = simultaneous_intervals({f"m{j}": d[:, j] for j in range(4)}, method="max-t", draws=400_000)
    for j in range(4):
        width = got[f"m{j}"][1] - got[f"m{j}"][0]
        assert width == pytest.approx(2 * crit * d[:, j].std(ddof=1) / math.sqrt(8), rel=1e-12)


def test_max_t_simultaneous_coverage() -> None:
    """300 repetitions of 4 methods (correlation 0.5) over 6 seeds, true means 0: all four intervals cover 0 in
    about 95 % of them (binomial sd 1.3 % at 300; the bounds are about ±3.5 sd)."""
    rng = np.random.default_rng(4)
    cov = 0.5 + 0.5 * np.eye(4)
    covered = 0
    for rep in range(300):
        d = rng.multivariate_normal(np.zeros(4), cov, size=6)
        got = simultaneous_intervals({f"m{j}": d[:, j] for j in range(4)}, method="max-t", draws=4000, seed=rep)
        covered += all(low <= 0 <= high for low, high in got.values())
    assert 0.905 <= covered / 300 <= 0.99


def test_max_t_needs_shared_seeds() -> None:
    with pytest.raises(ValueError):
        simultaneous_intervals({"a": [0.1, 0.2, 0.3], "b": [0.1, 0.2]}, method="max-t")


def test_friedman_matches_scipy() -> None:
    rng = np.random.default_rng(5)
    x = rng.normal(size=(10, 5))  # continuous: no ties, and no correction to make
    ours, theirs = friedman(x), stats.friedmanchisquare(*x.T)
    assert (ours.chi2, ours.p_chi2) == pytest.approx((theirs.statistic, theirs.pvalue), rel=1e-10)
    tied = rng.integers(0, 3, size=(12, 4)).astype(float)
    ours, theirs = friedman(tied, tie_correction=True), stats.friedmanchisquare(*tied.T)
    assert (ours.chi2, ours.p_chi2) == pytest.approx((theirs.statistic, theirs.pvalue), rel=1e-10)
    assert friedman(tied).chi2 < ours.chi2  # the correction only raises χ²
    # Iman–Davenport by hand: F = (n−1)χ² / (n(k−1) − χ²) on (k−1, (k−1)(n−1)) degrees of freedom
    res = friedman(x)
    f = 9 * res.chi2 / (10 * 4 - res.chi2)
    assert (res.f, res.p_f) == pytest.approx((f, stats.f.sf(f, 4, 36)), rel=1e-10)
    assert (res.n, res.k) == (10, 5)


def test_friedman_ranks_by_hand() -> None:
    res = friedman(np.array([[3.0, 2.0, 1.0], [3.0, 1.0, 1.0]]))  # higher is better: rank 1; ties averaged
    assert res.ranks == pytest.approx([1.0, 2.25, 2.75])
    same = friedman(np.array([[3.0, 2.0, 1.0]] * 4))  # every block alike: χ² = n(k−1), F = ∞
    assert same.chi2 == pytest.approx(8.0) and same.f == math.inf and same.p_f == 0.0


def test_friedman_demsar_worked_example() -> None:
    # Demšar 2006, section 3.2.2: average ranks 3.143, 2.000, 2.893, 1.964; χ²_F = 9.28, F_F = 3.69 (F(3, 39))
    res = friedman(DEMSAR_AUC)
    assert res.ranks == pytest.approx(list(DEMSAR_RANKS.values()), abs=5e-4)
    assert round(res.chi2, 2) == 9.28 and round(res.f, 2) == 3.69
    assert round(stats.f.ppf(0.95, 3, 39), 2) == 2.85 and res.p_f < 0.05  # he rejects at F(3, 39)'s 2.85


@pytest.mark.parametrize("alpha", [0.05, 0.10])
def test_nemenyi_q_against_demsar_table(alpha: float) -> None:
    for k, q in zip(range(2, 11), DEMSAR_Q[alpha]):
        q_ours = nemenyi_cd(k, 7, alpha) / math.sqrt(k * (k + 1) / 42)
        assert q_ours == pytest.approx(q, abs=1e-3)  # printed to 3 decimals (k = 3: 2.3437 against 2.343)


def test_nemenyi_cd_demsar_worked_example() -> None:
    assert round(nemenyi_cd(4, 14), 2) == 1.25  # Demšar 2006, section 3.2.2
    assert round(nemenyi_cd(4, 14, 0.10), 2) == 1.12
    # at 0.05 no pair differs (1.179 < 1.25); at 0.10 C4.5+m+cf is better than C4.5 (1.179 ≥ 1.12), his Figure 1
    assert cd_groups(DEMSAR_RANKS, nemenyi_cd(4, 14)) == [("C4.5+m+cf", "C4.5+m", "C4.5+cf", "C4.5")]
    assert cd_groups(DEMSAR_RANKS, nemenyi_cd(4, 14, 0.10)) == [("C4.5+m+cf", "C4.5+m", "C4.5+cf"), ("C4.5+cf", "C4.5")]


def test_cd_groups_by_hand() -> None:
    ranks = {"a": 1.0, "b": 2.0, "c": 3.0}
    assert cd_groups(ranks, 1.5) == [("a", "b"), ("b", "c")]
    assert cd_groups(ranks, 2.5) == [("a", "b", "c")]
    assert cd_groups(ranks, 1.0) == []  # less than cd: a difference of exactly cd separates
    assert cd_groups({"d": 3.0, "b": 1.2, "a": 1.0, "c": 1.4}, 0.5) == [("a", "b", "c")]  # d apart from all
    assert cd_groups({"y": 1.5, "x": 1.5, "z": 3.5}, 0.1) == [("x", "y")]  # ties: by name
    assert cd_groups({"a": 1.0, "b": 1.8, "c": 2.2, "d": 2.9}, 1.0) == [("a", "b"), ("b", "c"), ("c", "d")]
    assert cd_groups({"a": 1.0, "b": 1.8, "c": 2.2, "d": 2.7}, 1.0) == [("a", "b"), ("b", "c", "d")]


@pytest.mark.plots
def test_plot_cd_writes_a_png(tmp_path: Path) -> None:
    from PIL import Image

    path = plot_cd(DEMSAR_RANKS, nemenyi_cd(4, 14, 0.10), tmp_path / "cd.png", title="Demšar 2006, α = 0.10")
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and 5_000 < len(data) < 300_000
    with Image.open(path) as image:
        assert 500 < image.size[0] < 1000 and 150 < image.size[1] < 500  # about 7 in × 2.5 in at 110 dpi
    assert not list(tmp_path.glob(".*"))  # no temporary file left


def _counts(rng: np.random.Generator, seeds: int, scenes: int, classes: int) -> tuple[np.ndarray, np.ndarray]:
    union = rng.integers(0, 50, size=(seeds, scenes, classes)).astype(float)
    union[:, 1:, -1] = 0  # the last class is only in scene 0: absent from draws without it
    return np.floor(union * rng.uniform(0.2, 1.0, union.shape)), union


def _miou(inter: np.ndarray, union: np.ndarray, zero: bool = False) -> float:
    if zero:  # the official SSC mIoU: every class, one without a voxel scoring 0
        return sum(i / u if u > 0 else 0.0 for i, u in zip(inter, union)) / len(union)
    ious = [i / u for i, u in zip(inter, union) if u > 0]
    return sum(ious) / len(ious)


def _naive(inter: dict, union: dict, draws: int, level: float, seed: int,
           zero: bool = False) -> tuple[float, float, float]:
    """The bootstrap by loops, with the random draws in the documented order."""
    n_seeds, n_scenes, _ = inter["m"].shape
    rng = np.random.default_rng(seed)
    seeds = rng.integers(0, n_seeds, size=(draws, n_seeds))
    scenes = rng.integers(0, n_scenes, size=(draws, n_scenes))  # one draw of the scenes serves every seed
    reps = []
    for b in range(draws):
        diffs = []
        for s in seeds[b]:
            drawn = {k: [sum(a[k][s, j] for j in scenes[b]) for a in (inter, union)] for k in ("m", "b")}
            diffs.append(_miou(*drawn["m"], zero) - _miou(*drawn["b"], zero))
        reps.append(np.mean(diffs))
    est = np.mean([_miou(inter["m"][s].sum(0), union["m"][s].sum(0), zero)
                   - _miou(inter["b"][s].sum(0), union["b"][s].sum(0), zero) for s in range(n_seeds)])
    low, high = np.quantile(reps, [(1 - level) / 2, (1 + level) / 2])
    return est, low, high


def test_hierarchical_bootstrap_matches_a_loop() -> None:
    rng = np.random.default_rng(6)
    (im, um), (ib, ub) = _counts(rng, 3, 4, 3), _counts(rng, 3, 4, 3)
    inter, union = {"m": im, "b": ib}, {"m": um, "b": ub}
    got = hierarchical_bootstrap(inter, union, "m", "b", draws=200, seed=7)
    assert got == _naive(inter, union, 200, 0.95, 7)  # integer counts: the same sums, bit for bit
    assert got[1] < got[0] < got[2]


def test_hierarchical_bootstrap_with_the_official_miou_matches_a_loop() -> None:
    """absent="zero": a class absent from a draw scores 0 over every class (the table's mIoU), not left out."""
    rng = np.random.default_rng(8)
    (im, um), (ib, ub) = _counts(rng, 3, 4, 3), _counts(rng, 3, 4, 3)
    inter, union = {"m": im, "b": ib}, {"m": um, "b": ub}
    got = hierarchical_bootstrap(inter, union, "m", "b", draws=200, seed=7, absent="zero")
    assert got == pytest.approx(_naive(inter, union, 200, 0.95, 7, zero=True), rel=1e-12, abs=1e-15)
    assert got != hierarchical_bootstrap(inter, union, "m", "b", draws=200, seed=7)  # the last class is absent
    with pytest.raises(ValueError, match="absent"):
        hierarchical_bootstrap(inter, union, "m", "b", absent="drop")


def test_hierarchical_bootstrap_one_scene_is_the_seeds_bootstrap() -> None:
    rng = np.random.default_rng(8)
    (im, um), (ib, ub) = _counts(rng, 5, 1, 4), _counts(rng, 5, 1, 4)
    per_seed = np.array([_miou(im[s, 0], um[s, 0]) - _miou(ib[s, 0], ub[s, 0]) for s in range(5)])
    seeds = np.random.default_rng(0).integers(0, 5, size=(500, 5))  # the first draw: the seeds
    reps = [per_seed[row].mean() for row in seeds]
    expected = (per_seed.mean(), *np.quantile(reps, [0.05, 0.95]))
    got = hierarchical_bootstrap({"m": im, "b": ib}, {"m": um, "b": ub}, "m", "b", draws=500, level=0.9)
    assert got == pytest.approx(expected, rel=1e-12, abs=1e-15)


def test_hierarchical_bootstrap_is_reproducible_and_paired() -> None:
    rng = np.random.default_rng(9)
    (im, um), (ib, ub) = _counts(rng, 4, 6, 5), _counts(rng, 4, 6, 5)
    inter, union = {"m": im, "b": ib}, {"m": um, "b": ub}
    first = hierarchical_bootstrap(inter, union, "m", "b", seed=3)
    assert hierarchical_bootstrap(inter, union, "m", "b", seed=3) == first
    assert hierarchical_bootstrap(inter, union, "m", "b", seed=4) != first
    assert hierarchical_bootstrap({"m": im, "b": im}, {"m": um, "b": um}, "m", "b") == (0.0, 0.0, 0.0)


def test_hierarchical_bootstrap_sees_the_scenes_that_the_seeds_do_not() -> None:
    # every seed alike: the per-seed differences have no spread, but the gain varies from scene to scene
    rng = np.random.default_rng(10)
    (im, um), (ib, ub) = _counts(rng, 1, 8, 3), _counts(rng, 1, 8, 3)
    inter = {"m": np.repeat(im, 4, axis=0), "b": np.repeat(ib, 4, axis=0)}
    union = {"m": np.repeat(um, 4, axis=0), "b": np.repeat(ub, 4, axis=0)}
    est, low, high = hierarchical_bootstrap(inter, union, "m", "b")
    assert low < est < high and high - low > 0.01
