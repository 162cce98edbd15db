"""The metric registry (pipeline.evaluation.metrics): one definition per name, read by the summary, the printed
tables and the recordings; one nees()."""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest

from pipeline.evaluation import metrics
from pipeline.evaluation.metrics import Metric, format_value, lookup, nees, register
from tests.helpers.config import smoke_experiments



def test_small_values_keep_their_significant_digits():
    """0.0023 m/s^2 printed as 0.00 said 'zero' (the printed table used two decimals for everything)."""
    assert format_value("acceleration_rmse", 0.0023) == "0.00230"
    assert format_value("position_rmse", 46.6712) == "46.67"
    assert format_value("compute_seconds", 0.0749) == "0.0749"
    assert format_value("detections", 13.0) == "13"
    assert format_value("compute_pct_of_reference", 56.54) == "56.5"
    assert format_value("nees", float("nan")) == ""
    assert format_value("an_unregistered_metric", 0.5) == "0.500"


def test_a_name_has_one_meaning():
    with pytest.raises(ValueError, match="one name, one meaning"):
        register(Metric("position_rmse", "ft"))
    register(Metric("position_rmse", "m", label="pos RMSE"))        # the same definition again is fine


def test_count_metrics_are_summed_over_a_window_and_the_rest_averaged():
    assert metrics.is_count("detections_axis_z") and not metrics.is_count("nees")


@pytest.fixture(params=["numpy", "compiled"])
def nees_path(request, monkeypatch):
    """Both ways nees() solves (metrics.COMPILED_ENTRIES decides by size)."""
    monkeypatch.setattr(metrics, "COMPILED_ENTRIES", 0 if request.param == "compiled" else 10**18)
    return request.param


def test_nees_by_hand(nees_path):
    error = np.array([[1.0, 2.0], [np.nan, 0.0], [3.0, 0.0]])
    covariance = np.array([np.diag([1.0, 4.0]), np.eye(2), [[2.0, 0.0], [0.0, 0.0]]])
    value = nees(error, covariance)
    assert value[0] == pytest.approx(1.0 + 1.0)                 # 1^2/1 + 2^2/4
    assert np.isnan(value[1])                                    # no estimate: NaN, not an error
    assert value[2] == pytest.approx(9.0 / 2.0)                 # singular: the pseudo-inverse


def test_the_compiled_nees_agrees_with_numpys_solve(monkeypatch):
    """Random well- and ill-conditioned, indefinite (pivoting), singular, NaN and inf covariances of
    6 states over (runs, steps, targets): the compiled solve equals numpy's to rounding."""
    rng = np.random.default_rng(5)
    A = rng.standard_normal((4, 50, 2, 6, 6))
    P = A @ np.swapaxes(A, -1, -2) + 1e-3 * np.eye(6)
    P[0, :10] *= 10.0 ** rng.uniform(-6, 6, size=(10, 2, 1, 1))
    P[1, 3, 0] = np.diag([1.0, -2.0, 3.0, 1.0, 1.0, 1.0])[[1, 0, 2, 3, 4, 5]]   # a zero leading pivot
    P[1, 4, 1] = np.diag([1.0, 1.0, 0.0, 1.0, 1.0, 1.0])                        # singular
    P[2, 5, 0, 1, 1] = np.inf
    error = rng.standard_normal((4, 50, 2, 6))
    error[3, 7, 1, 2] = np.nan
    values = {}
    for path, threshold in (("numpy", 10**18), ("compiled", 0)):
        monkeypatch.setattr(metrics, "COMPILED_ENTRIES", threshold)
        values[path] = nees(error, P)
    np.testing.assert_array_equal(np.isnan(values["compiled"]), np.isnan(values["numpy"]))
    np.testing.assert_allclose(values["compiled"], values["numpy"], rtol=1e-9)
    assert np.isnan(values["numpy"][2, 5, 0]) and np.isnan(values["numpy"][3, 7, 1])
    # a PackedCovariance is solved from its float32 triangles: as its unpacked matrices are
    from pipeline.storage.schemas import PackedCovariance
    upper = np.triu_indices(6)
    packed = PackedCovariance(P[..., upper[0], upper[1]].astype(np.float32), 6)
    np.testing.assert_array_equal(nees(error, packed), nees(error, np.asarray(packed)))


@pytest.mark.parametrize("experiment, smoke", smoke_experiments())
def test_every_metric_a_study_writes_is_registered_with_a_unit(smoke_runs, experiment, smoke):
    out, _ = smoke_runs(experiment)                 # the session's smoke run (conftest.SmokeRuns)
    names = set(out.metrics["series"].unique().to_list()) | set(out.summary["series"].unique().to_list())
    unregistered = sorted(n for n in names if lookup(n) is None)
    assert not unregistered, f"{experiment}: metrics without a registry entry: {unregistered}"
    units = out.summary.filter(pl.col("unit") == "")["series"].unique().to_list()
    assert not units, f"{experiment}: summary rows without a unit: {units}"


def test_one_query_finds_the_position_rmse_of_every_study(smoke_runs):
    """'Lowest position RMSE per experiment' silently dropped study 002, whose names carried the radar
    and target (position_rmse_s2_t32): metric is now the quantity, with component / sensor / target columns."""
    from pipeline.results.query import query
    studies = smoke_experiments()
    for experiment, _ in studies:
        smoke_runs(experiment)                      # the session's smoke runs, all under one root
    best = query("SELECT experiment, MIN(value) AS lowest FROM summary WHERE metric = 'position_rmse' "
                 "AND component IS NULL GROUP BY experiment "
                 "ORDER BY experiment", root=smoke_runs.root)
    assert best["experiment"].to_list() == sorted(e for e, _ in studies)
    per_target = query("SELECT DISTINCT sensor, target FROM summary WHERE series = 'position_rmse_s2_t32'",
                       root=smoke_runs.root)
    assert per_target.rows() == [(2, 32)]
