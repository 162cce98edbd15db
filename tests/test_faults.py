"""Numerical-fault flags: each fault injected into an otherwise healthy estimate is flagged at
its run and step only."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.evaluation.faults import FAULTS, FaultChecks, describe, fault_flags, fault_summary


@pytest.fixture(params=["numpy", "compiled"])
def checks_path(request, monkeypatch):
    """Both ways of checking the matrices (pipeline.evaluation.faults.COMPILED_ENTRIES decides by size)."""
    from pipeline.evaluation import faults
    monkeypatch.setattr(faults, "COMPILED_ENTRIES", 0 if request.param == "compiled" else 10**18)
    return request.param


def healthy(R=5, K=8, n=4, seed=0):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((R, K, n, n))
    P = A @ np.swapaxes(A, -1, -2) + n * np.eye(n)
    x = rng.standard_normal((R, K, n))
    x[:, 0] = np.nan                       # no estimate at the first scan: not a fault
    P[:, 0] = np.nan
    return x, P


def test_a_healthy_estimate_has_no_flag(checks_path):
    x, P = healthy()
    assert not fault_flags(x, P, FaultChecks(nees_bound=1e6), error=np.nan_to_num(x)).any()


@pytest.mark.parametrize("fault", ["nonfinite_state", "inf_covariance", "asymmetric", "not_positive_definite",
                                   "nees_above_bound", "weights_underflow"])
def test_each_injected_fault_is_flagged_at_its_run_and_step_only(fault, checks_path):
    x, P = healthy()
    error = np.nan_to_num(x.copy())
    underflow = np.zeros(x.shape[:2], dtype=bool)
    run, step = 3, 5
    expected = {"nonfinite_state": "nonfinite", "inf_covariance": "nonfinite"}.get(fault, fault)
    if fault == "nonfinite_state":
        x[run, step, 1] = np.nan
    elif fault == "inf_covariance":
        P[run, step, 2, 2] = np.inf
    elif fault == "asymmetric":
        P[run, step, 0, 1] += 1e-3 * np.abs(P[run, step]).max()
    elif fault == "not_positive_definite":
        P[run, step] = np.diag([1.0, 1.0, -1e-3, 1.0])
    elif fault == "nees_above_bound":
        error[run, step] = 1e3
    else:
        underflow[run, step] = True
    flags = fault_flags(x, P, FaultChecks(nees_bound=100.0), error=error, weights_underflow=underflow)
    assert flags[run, step] == FAULTS[expected] and describe(int(flags[run, step])) == [expected]
    flags[run, step] = 0
    assert not flags.any()                 # every other run and step is clean
    summary = fault_summary(np.where(np.arange(5)[:, None] == run, FAULTS[expected], 0).astype(np.uint8))
    assert summary["diverged_runs"] == 1 and summary[f"fault_runs_{expected}"] == 1


def test_a_reduced_state_is_not_a_fault_but_a_nan_inside_it_is(checks_path):
    """Components a filter does not estimate at a step (NaN in the state and in their covariance rows
    and columns, the rest finite: study 003's KF + MGEKF while active) are not flagged; a NaN that
    reaches the estimated block is."""
    state = np.zeros((1, 3, 6))
    covariance = np.broadcast_to(np.eye(6), (1, 3, 6, 6)).copy()
    state[0, 1, 4:] = np.nan                                          # step 1: no acceleration estimate
    covariance[0, 1, 4:, :] = covariance[0, 1, :, 4:] = np.nan
    state[0, 2, 4:] = np.nan                                          # step 2: the same, and a NaN in the block
    covariance[0, 2, 4:, :] = covariance[0, 2, :, 4:] = np.nan
    covariance[0, 2, 0, 1] = np.nan
    flags = fault_flags(state, covariance, FaultChecks(nees_bound=100.0), np.ones((1, 3, 6)))
    assert flags[0, 0] == 0 and flags[0, 1] == 0
    assert describe(int(flags[0, 2])) == ["nonfinite"]


def test_per_target_flags_reduce_to_the_step(checks_path):
    x, P = healthy(R=2, K=3, n=2)
    x = np.repeat(x[:, :, None], 3, axis=2)
    P = np.repeat(P[:, :, None], 3, axis=2)
    P[1, 2, 2] = np.diag([1.0, -1.0])
    flags = fault_flags(x, P)
    assert flags.shape == (2, 3) and flags[1, 2] == FAULTS["not_positive_definite"] and flags.sum() == flags[1, 2]


def test_the_compiled_checks_decide_as_numpys_on_a_mixed_batch(monkeypatch):
    """Healthy, asymmetric (above and below the tolerance), indefinite, singular, NaN/inf, reduced and
    not-yet-started matrices, over targets too: the compiled pass flags what numpy's does."""
    from pipeline.evaluation import faults
    rng = np.random.default_rng(7)
    x, P = healthy(R=6, K=40, n=6, seed=3)
    x = np.repeat(x[:, :, None], 2, axis=2)
    P = np.repeat(P[:, :, None], 2, axis=2)
    cells = [(r, k, t) for r in range(6) for k in range(1, 40) for t in range(2)]
    picks = rng.permutation(len(cells))[:120]
    for kind, index in zip(np.arange(120) % 8, picks):
        r, k, t = cells[index]
        if kind == 0:
            P[r, k, t, 0, 3] += 1e-3 * np.abs(P[r, k, t]).max()
        elif kind == 1:
            P[r, k, t, 0, 3] += 1e-12 * np.abs(P[r, k, t]).max()       # within the tolerance
        elif kind == 2:
            P[r, k, t] = np.diag([1.0, 2.0, -1e-3, 1.0, 1.0, 1.0])
        elif kind == 3:
            P[r, k, t] = np.diag([1.0, 1.0, 0.0, 1.0, 1.0, 1.0])           # singular (a zero pivot)
        elif kind == 4:
            P[r, k, t, 2, 2] = np.inf
        elif kind == 5:
            x[r, k, t, 4:] = np.nan
            P[r, k, t, 4:, :] = P[r, k, t, :, 4:] = np.nan              # a reduced estimate
        elif kind == 6:
            x[r, k, t, 1] = np.nan
        else:
            P[r, k, t] = -P[r, k, t]
    x[5, :] = np.nan                                                     # a run that never starts
    P[5, :] = np.nan
    results = {}
    for path, threshold in (("numpy", 10**18), ("compiled", 0)):
        monkeypatch.setattr(faults, "COMPILED_ENTRIES", threshold)
        results[path] = fault_flags(x, P, FaultChecks(nees_bound=50.0), error=np.nan_to_num(x))
    np.testing.assert_array_equal(results["compiled"], results["numpy"])
    assert len(set(np.unique(results["numpy"]))) >= 5                    # the mixture reached several bits


def test_bad_thresholds_are_refused_with_the_key():
    with pytest.raises(ValueError, match="faults.nees_bound"):
        FaultChecks(nees_bound=-1.0)
    with pytest.raises(ValueError, match="faults.symmetry_tolerance"):
        FaultChecks(symmetry_tolerance=float("nan"))


def test_the_pipeline_flags_injected_faults_per_run_and_step_and_counts_them(tmp_path):
    import polars as pl
    from hydra import compose, initialize_config_dir

    from pipeline.run.runner import RunContext, run_experiment
    from tests.helpers.config import CONF

    overrides = ["mc.runs=5", "scenario.steps=30", "filters.fsimm._target_=tests.faulty_filters.FaultyFSIMM", "plugins.packages=[tests]",
                 "variants=[fsimm,vsimm]"]
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfg = compose("config", overrides=[f"paths.artifacts={tmp_path}", "record.enabled=false", *overrides])
    ctx = RunContext(tmp_path / "runs" / "faulty", tmp_path, overrides)
    outcome = run_experiment(cfg, ctx)

    table = pl.read_parquet(ctx.run_dir / "estimates" / "fsimm.parquet")
    flagged = table.filter(pl.col("fault") != 0).select("run", "step", "fault").sort("run", "step")
    expected = ([(1, 10, FAULTS["asymmetric"]), (3, 15, FAULTS["not_positive_definite"])]
                + [(2, k, FAULTS["nonfinite"]) for k in range(20, table["step"].max() + 1)])
    assert sorted(flagged.rows()) == sorted(expected)
    assert (pl.read_parquet(ctx.run_dir / "estimates" / "vsimm.parquet")["fault"] == 0).all()

    def count(variant_key, metric):
        return outcome.summary.filter((pl.col("variant_key") == variant_key) & (pl.col("series") == metric))["value"][0]
    assert count("fsimm", "diverged_runs") == 3 and count("vsimm", "diverged_runs") == 0
    assert count("fsimm", "fault_runs_nonfinite") == 1 and count("fsimm", "fault_runs_asymmetric") == 1
    # the other runs' results are kept: the RMSE of the diverged steps comes from the 4 healthy runs
    rmse = outcome.metrics.filter((pl.col("variant_key") == "fsimm") & (pl.col("series") == "position_rmse"))
    assert rmse.filter(pl.col("step") >= 20)["value"].is_finite().all()


@pytest.mark.parametrize("engine", ["numba", "numpy"])
@pytest.mark.parametrize("auxiliary", [True, False])
def test_a_particle_filter_whose_weights_all_underflow_restarts_them_and_flags_the_step(auxiliary, engine):
    """Run 1's bearings at scan 4 are infinite: every residual, so every log weight, is NaN (both
    stages of the AMMPF); the run restarts from uniform weights, flagged, and goes on. Injected
    in the data, so the compiled scan (which calls no Python likelihood) is tested the same way."""
    import dataclasses

    from filters.particle import MultipleModelParticleFilter
    from tests.helpers.filter_inputs import buoy_reports

    _, reports = buoy_reports(runs=3, duration=60.0)
    healthy = MultipleModelParticleFilter(particles=100, auxiliary=auxiliary, chunk_runs=3, workers=1,
                                          engine=engine).run(reports)
    z = reports.z.copy()
    z[1, 4] = np.inf
    with np.errstate(invalid="ignore"):                # inf - inf in the numpy loop's residuals
        broken = MultipleModelParticleFilter(particles=100, auxiliary=auxiliary, chunk_runs=3, workers=1,
                                             engine=engine).run(dataclasses.replace(reports, z=z))
    flags = broken.extras["weights_underflow"]
    assert flags.shape == (3, reports.time.size) and flags.sum() == 1 and flags[1, 4]
    assert np.isfinite(broken.state).all()              # the run goes on from uniform weights
    np.testing.assert_array_equal(broken.state[[0, 2]], healthy.state[[0, 2]])   # the other runs are untouched
    assert not healthy.extras["weights_underflow"].any()
    masks = fault_flags(broken.state, broken.covariance, weights_underflow=flags)
    assert (masks[1] == FAULTS["weights_underflow"]).sum() == 1


def test_the_nees_bound_flags_diverging_steps_through_the_pipeline(tmp_path):
    import polars as pl
    from hydra import compose, initialize_config_dir

    from pipeline.run.runner import RunContext, run_experiment
    from tests.helpers.config import CONF

    def run(name, bound):
        overrides = ["mc.runs=4", "scenario.steps=30", "variants=[fsimm]", f"faults.nees_bound={bound}"]
        with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
            cfg = compose("config", overrides=[f"paths.artifacts={tmp_path}", "record.enabled=false", *overrides])
        ctx = RunContext(tmp_path / "runs" / name, tmp_path, overrides)
        return run_experiment(cfg, ctx), ctx

    _, loose = run("loose", 1e9)
    outcome, tight = run("tight", 1e-3)               # far below any NEES: every estimated step diverges
    assert (pl.read_parquet(loose.run_dir / "estimates" / "fsimm.parquet")["fault"] == 0).all()
    table = pl.read_parquet(tight.run_dir / "estimates" / "fsimm.parquet")
    started = table.filter(pl.col("x").arr.first().is_not_nan())
    assert (started["fault"] == FAULTS["nees_above_bound"]).all()
    diverged = outcome.summary.filter(pl.col("series") == "fault_runs_nees_above_bound")["value"][0]
    assert diverged == 4


def test_an_estimate_lost_to_1e15_m_is_counted_as_diverged():
    """Issue 38: MIE A on a long ADS-B flight ran 8.7e8 m off a truth within 3.5e5 m (RMSE up to 1e15 m
    elsewhere) with a finite, symmetric, positive definite covariance: every numerical check passed and
    0 runs were flagged. An error beyond faults.divergence_factor x the truth's scale is a fault."""
    from filters.base import TrackEstimate
    from pipeline.data import Truth
    from pipeline.studies.single_target import SingleTargetStudy

    R, K = 4, 30
    rng = np.random.default_rng(3)
    true = np.zeros((R, K, 1, 6))
    true[..., 0] = 200.0 * np.arange(K)[None, :, None] + 30_000.0        # a target 30-36 km out, 200 m/s
    true[..., 3] = 200.0
    truth = Truth(np.arange(K, dtype=float), true, ("x", "y", "z", "vx", "vy", "vz"))
    state = true[:, :, 0, :] + 100.0 * rng.standard_normal((R, K, 6))      # tracking badly is no fault
    state[2, 20:, :3] = 1e15                                               # run 2 lost from scan 20
    covariance = np.broadcast_to(np.diag([1e6] * 6), (R, K, 6, 6)).copy()
    covariance[2, 20:] *= 1e20                                             # huge, but PD and symmetric
    estimate = TrackEstimate(truth.time, state, covariance)
    flags = SingleTargetStudy().fault_flags(estimate, truth, FaultChecks())
    assert (flags[2, 20:] == FAULTS["beyond_scale"]).all() and not flags[2, :20].any()
    assert not flags[[0, 1, 3]].any()
    assert fault_summary(flags)["diverged_runs"] == 1 and fault_summary(flags)["fault_runs_beyond_scale"] == 1
    # the bound is relative to the scenario's scale: the same error on a truth 1e14 m out is no fault
    far = Truth(truth.time, true * 1e10, truth.state_names)
    shifted = TrackEstimate(truth.time, state + (far.state - true)[:, :, 0, :], covariance)
    assert not SingleTargetStudy().fault_flags(shifted, far, FaultChecks())[2].any()
    assert not SingleTargetStudy().fault_flags(estimate, truth, FaultChecks(divergence_factor=None)).any()


def test_divergence_factor_is_checked():
    with pytest.raises(ValueError, match="faults.divergence_factor: 0 must be a number > 0"):
        FaultChecks(divergence_factor=0)
