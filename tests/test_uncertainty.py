"""Monte Carlo uncertainty (pipeline/evaluation/uncertainty.py) against closed forms and scipy.

- a mean over runs: Student's t interval, exactly mean +- t(n-1) s / sqrt(n);
- 0/1 per run: the exact Clopper-Pearson interval of scipy.stats.binomtest;
- an RMSE of N(0, sigma^2) errors (a known variance): the bootstrap's standard error is the delta
  method's sigma / sqrt(2 n), and its intervals cover sigma about 95 % of the time;
- the BCa interval is scipy.stats.bootstrap's on the same resamples;
- paired comparisons: a constructed per-run difference is found with its size, an identical variant
  is not "resolved", and the Wilcoxon p-value is scipy's.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from pipeline.evaluation.uncertainty import (Estimated, RunValues, WindowStatistic, bootstrap_values,
                                  stream_seed, summarize)


def one(values: np.ndarray, across: str, series: str = "m", variant: str = "a") -> Estimated:
    rv = RunValues(np.asarray(values, dtype=float)[:, None] if np.ndim(values) == 1 else values, across)
    return Estimated(variant, series, "all", WindowStatistic(rv, np.arange(rv.values.shape[1])))


def test_a_mean_over_runs_gets_the_t_interval():
    sample = np.random.default_rng(3).normal(5.0, 2.0, size=40)
    intervals, _ = summarize([one(sample, "mean")], None, seed=1)
    got = intervals[0]
    half = stats.t.ppf(0.975, 39) * sample.std(ddof=1) / np.sqrt(40)
    assert got.method == "t" and got.n_valid_runs == 40
    assert got.value == pytest.approx(sample.mean(), rel=1e-12)
    assert got.low == pytest.approx(sample.mean() - half, rel=1e-12)
    assert got.high == pytest.approx(sample.mean() + half, rel=1e-12)
    assert got.standard_error == pytest.approx(sample.std(ddof=1) / np.sqrt(40), rel=1e-12)


def test_a_window_mean_of_a_per_step_mean_is_the_mean_of_the_runs_own_means():
    values = np.random.default_rng(4).normal(size=(30, 8))
    values[:, :2] = np.nan                                   # the same steps missing in every run
    row = Estimated("a", "m", "w", WindowStatistic(RunValues(values, "mean"), np.arange(8)))
    got = summarize([row], None, seed=1)[0][0]
    own = np.nanmean(values, axis=1)
    assert got.method == "t"
    assert got.low == pytest.approx(own.mean() - stats.t.ppf(0.975, 29) * own.std(ddof=1) / np.sqrt(30))


def test_runs_valid_at_different_steps_are_bootstrapped_not_averaged():
    values = np.random.default_rng(5).normal(size=(30, 8))
    values[0, 3] = np.nan
    row = Estimated("a", "m", "w", WindowStatistic(RunValues(values, "mean"), np.arange(8)))
    assert summarize([row], None, seed=1)[0][0].method.startswith("bootstrap")


def test_a_fraction_of_runs_gets_the_exact_binomial_interval():
    lost = np.array([1.0] * 7 + [0.0] * 43)
    got = summarize([one(lost, "mean")], None, seed=1)[0][0]
    exact = stats.binomtest(7, 50).proportion_ci(confidence_level=0.95, method="exact")
    assert got.method == "exact" and got.value == pytest.approx(0.14)
    assert (got.low, got.high) == pytest.approx((exact.low, exact.high), rel=1e-12)


def test_a_count_summed_over_runs_scales_the_interval_by_the_runs():
    flags = np.zeros((50, 10))
    flags[:9, 4] = 1.0                                       # 9 of 50 runs detect once
    row = Estimated("a", "detections", "w", WindowStatistic(RunValues(flags, "sum"), np.arange(10), "sum"))
    got = summarize([row], None, seed=1)[0][0]
    exact = stats.binomtest(9, 50).proportion_ci(method="exact")
    assert got.value == 9.0 and got.method == "exact"
    assert (got.low, got.high) == pytest.approx((50 * exact.low, 50 * exact.high))


def test_the_rmse_of_a_known_variance_has_the_delta_method_error_and_covers_sigma():
    sigma, runs = 3.0, 200
    rng = np.random.default_rng(6)
    covered, errors = 0, []
    trials = 100
    for trial in range(trials):
        squared = (sigma * rng.standard_normal(runs)) ** 2
        got = summarize([one(squared, "rms")], None, seed=trial, resamples=1000)[0][0]
        assert got.method == "bootstrap BCa"
        covered += got.low <= sigma <= got.high
        errors.append(got.standard_error)
    # sqrt of a mean of sigma^2 chi2(1) / n: standard error sigma / sqrt(2 n) (delta method)
    assert np.mean(errors) == pytest.approx(sigma / np.sqrt(2 * runs), rel=0.1)
    assert 0.88 <= covered / trials <= 1.0


def test_bca_is_scipys_on_the_same_resamples():
    squared = np.random.default_rng(7).gamma(0.7, 2.0, size=60)
    rv = RunValues(squared[:, None], "rms")
    statistic = WindowStatistic(rv, [0])
    seed = stream_seed(11, "check")
    low, high, se, method, _ = bootstrap_values([(rv, [statistic])], 60, lambda v: np.stack(v), 1, seed, 0.95, 999)

    def rmse(sample, axis=-1):
        return np.sqrt(np.mean(sample, axis=axis))

    reference = stats.bootstrap((squared,), rmse, n_resamples=999, method="BCa", vectorized=True,
                                rng=np.random.default_rng(seed))
    assert method[0] == "bootstrap BCa"
    assert low[0] == pytest.approx(reference.confidence_interval.low, rel=1e-10)
    assert high[0] == pytest.approx(reference.confidence_interval.high, rel=1e-10)
    assert se[0] == pytest.approx(reference.standard_error, rel=1e-10)


def test_a_constant_statistic_has_the_point_as_its_interval():
    got = summarize([one(np.full(20, 13.0), "mean")], None, seed=1)[0][0]
    assert (got.low, got.high, got.standard_error) == (13.0, 13.0, 0.0)


def test_a_constructed_paired_difference_is_resolved_with_its_size():
    rng = np.random.default_rng(8)
    runs = 60
    base = rng.normal(10.0, 3.0, size=runs)                 # run-to-run spread much larger than the effect
    rows = [one(base, "mean", variant="ref"), one(base + 0.5 + rng.normal(0, 0.2, runs), "mean", variant="better"),
            one(base.copy(), "mean", variant="same")]
    _, comparisons = summarize(rows, "ref", seed=2)
    by = {c["variant_key"]: c for c in comparisons}
    better = by["better"]
    assert better["difference_low"] < 0.5 < better["difference_high"]
    assert better["difference_high"] - better["difference_low"] < 0.25     # pairing removes the spread of 3
    assert better["resolved"] and better["wilcoxon_p"] < 1e-6
    expected = stats.wilcoxon(rows[1].statistic.per_run() - base).pvalue
    assert better["wilcoxon_p"] == pytest.approx(expected)
    assert better["ratio_low"] < (base.mean() + 0.5) / base.mean() * 1.01
    same = by["same"]
    assert same["difference"] == 0.0 and same["wilcoxon_p"] == 1.0 and not same["resolved"]


def test_an_unpaired_look_would_not_resolve_what_the_paired_one_does():
    rng = np.random.default_rng(9)
    base = rng.normal(10.0, 3.0, size=40)
    rows = [one(base, "mean", variant="ref"), one(base + 0.3, "mean", variant="v")]
    intervals, comparisons = summarize(rows, "ref", seed=3)
    assert intervals[0].low < intervals[1].value < intervals[0].high        # the intervals overlap
    assert comparisons[0]["resolved"]


def test_per_run_values_are_each_runs_own_statistic():
    squared = np.array([[1.0, 9.0], [4.0, np.nan]])
    statistic = WindowStatistic(RunValues(squared, "rms"), [0, 1])
    np.testing.assert_allclose(statistic.per_run(), [np.sqrt(5.0), 2.0])
    assert statistic.value() == pytest.approx(np.mean([np.sqrt(2.5), 3.0]))
    pooled = WindowStatistic(RunValues(squared, "rms"), [0, 1], "pool")
    assert pooled.value() == pytest.approx(np.sqrt(14.0 / 3))


def test_a_ratio_to_a_bound_shares_the_rmse_runs():
    squared = np.random.default_rng(10).gamma(2.0, size=(30, 5))
    rmse = RunValues(squared, "rms")
    bound = np.full(5, 2.0)
    ratio = WindowStatistic(rmse.over(bound), np.arange(5))
    plain = WindowStatistic(rmse, np.arange(5))
    intervals, _ = summarize([Estimated("a", "r", "w", ratio), Estimated("a", "m", "w", plain)], None, seed=1)
    assert intervals[0].value == pytest.approx(intervals[1].value / 2)
    assert intervals[0].low == pytest.approx(intervals[1].low / 2)


def test_bad_kinds_are_refused():
    with pytest.raises(ValueError, match="across_runs"):
        RunValues(np.zeros((2, 2)), "average")
    with pytest.raises(ValueError, match="over_steps"):
        WindowStatistic(RunValues(np.zeros((2, 2)), "mean"), [0], "median")


def test_the_resampled_median_is_numpys_nanmedian_with_nans_anywhere():
    from pipeline.evaluation.uncertainty import nanmedian_last
    drawn = np.random.default_rng(12).normal(size=(7, 5, 9))
    drawn[drawn > 1.0] = np.nan                               # some columns lose several values
    drawn[:, 3, :] = np.nan                                   # one column has none
    with np.errstate(all="ignore"), pytest.warns(RuntimeWarning):
        expected = np.nanmedian(drawn, axis=-1)
    np.testing.assert_array_equal(nanmedian_last(drawn), expected)
    clean = np.random.default_rng(13).normal(size=(4, 3, 6))
    np.testing.assert_array_equal(nanmedian_last(clean), np.median(clean, axis=-1))


def test_a_bootstrapped_median_over_runs_and_members_matches_a_direct_resample():
    values = np.random.default_rng(14).gamma(2.0, size=(20, 6, 4))
    values[3, 2, :] = np.nan
    rv = RunValues(values, "median")
    statistic = WindowStatistic(rv, np.arange(6))
    low, high, se, method, _ = bootstrap_values([(rv, [statistic])], 20, lambda v: np.stack(v), 1,
                                             stream_seed(1, "m"), 0.95, 400)
    drawn = np.random.default_rng(stream_seed(1, "m")).integers(0, 20, size=(400, 20))
    direct = np.array([np.nanmean(np.nanmedian(np.moveaxis(values[i], 2, 1).reshape(-1, 6), axis=0))
                       for i in drawn])
    assert se[0] == pytest.approx(direct.std(ddof=1), rel=1e-9)


def _numpy_resampled_median(items: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The weighed median as numpy computed it before the compiled pass: the (B, I, C) weights, their
    cumulative sum, the first index reaching each middle rank."""
    order = np.argsort(np.where(np.isnan(items), np.inf, items), axis=0, kind="stable")
    values = np.take_along_axis(items, order, axis=0)
    runs = np.arange(items.shape[0])[order]
    weight = counts[:, runs] * np.isfinite(values)
    cumulative = np.cumsum(weight, axis=1)
    n = cumulative[:, -1, :]
    lower = np.argmax(cumulative >= ((n - 1) // 2 + 1)[:, None, :], axis=1)
    upper = np.argmax(cumulative >= (n // 2 + 1)[:, None, :], axis=1)
    step = np.arange(values.shape[1])
    with np.errstate(invalid="ignore"):
        middle = 0.5 * (values[lower, step] + values[upper, step])
    return np.where(n > 0, middle, np.nan)


def test_the_compiled_resampled_median_equals_the_numpy_weighing_bit_for_bit():
    """Runs x steps with NaN, +inf and -inf (no weight, wherever they sort), a step with no finite
    value, bootstrap draws and jackknife leave-one-out weights: equal to the numpy formula."""
    from pipeline.evaluation.uncertainty import SortedItems
    rng = np.random.default_rng(21)
    items = rng.gamma(2.0, size=(31, 40))
    items[rng.random(items.shape) < 0.1] = np.nan
    items[rng.random(items.shape) < 0.03] = np.inf
    items[rng.random(items.shape) < 0.03] = -np.inf
    items[:, 7] = np.nan
    items[:, 8] = np.round(items[:, 8], 1)                    # ties
    draws = rng.integers(0, 31, size=(300, 31))
    counts = np.zeros((300, 31))
    np.add.at(counts, (np.arange(300)[:, None], draws), 1.0)
    for weights in (counts, 1.0 - np.eye(31)):
        got = SortedItems(items).median(weights)
        np.testing.assert_array_equal(got, _numpy_resampled_median(items, weights))
        assert np.isnan(got[:, 7]).all()


def test_statistics_resampled_apart_pair_exactly_as_resampled_together():
    """The evaluation resamples each variant when it is measured (pipeline.evaluation.uncertainty.resample) and
    pairs them at the end; the comparisons must equal the joint bootstrap's (bootstrap_values with
    every row at once) bit for bit. A count over many runs x steps is resampled in float32
    (FLOAT32_CELLS): pairs formed in float64 from a float64-cast all-runs value gave other ratio
    intervals (study 000 at 2500 runs: 12 comparison rows, e.g. 12.890581 against 12.891265)."""
    from pipeline.evaluation.uncertainty import FLOAT32_CELLS, resample

    rng = np.random.default_rng(11)
    runs, steps = 120, FLOAT32_CELLS // 120 + 10                  # over the float32 threshold
    counts = {v: (rng.random((runs, steps)) < p).astype(float) for v, p in (("ref", 0.02), ("v", 0.03))}
    rows = [Estimated(v, "detections", "all", WindowStatistic(RunValues(c, "sum"), np.arange(steps), "sum"))
            for v, c in counts.items()]
    apart = [Estimated(r.variant, r.series, r.window, resample([r.statistic], seed=5)[0]) for r in rows]
    _, comparisons = summarize(apart, "ref", seed=5)
    # the joint bootstrap, as summarize computed it before the rows could be resampled apart
    groups = [(r.statistic.values, [r.statistic]) for r in rows]

    def combine(values):
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.stack(values + [values[1] - values[0], values[1] / values[0]])

    low, high, _, _, _ = bootstrap_values(groups, runs, combine, 4, stream_seed(5, "summary"), 0.95, 2000)
    assert apart[0].statistic.distribution.dtype == np.float32     # the float32 path is the one tested
    (c,) = comparisons
    assert (c["difference_low"], c["difference_high"], c["ratio_low"], c["ratio_high"]) == \
        (low[2], high[2], low[3], high[3])
