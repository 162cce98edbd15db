"""Study 003's normalised innovation squared: each update's nu' S^-1 nu against a hand computation
(bearing-only, active MGEKF / EKF, converted KF), the run-averaged NIS inside its 95 % chi-square
band when the filter's model is the truth's, and the pipeline's metrics and recording carrying
``nis`` / ``nis_lower`` / ``nis_upper`` for every variant (with the NEES band beside NEES)."""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest
from hydra import compose, initialize_config_dir

from filters.mgekf import (
    KFPlusMGEKF, OnlyMGEKF, PlainEKF, SonarReports, bearing_range, converted_update, nonlinear_update,
    relative_motion_model,
)
from pipeline.run.runner import RunContext, run_experiment
from pipeline.evaluation.evaluate import nis_metrics
from tests.helpers.config import CONF
from tests.helpers.rrd_reading import entity_index, read_chunks, temporal

BEARING_STD, RANGE_STD = 0.01, 10.0                      # [rad], [m] for the single-step cases


def _prior(n: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """One run at (3000, 4000) m (r = 5000, beta_hat = atan2(3, 4)) with P_xy = diag(100^2, 200^2)."""
    x = np.zeros((1, n))
    x[0, :4] = [3000.0, 4000.0, -2.0, 1.0]
    P = np.diag([100.0**2, 200.0**2, 4.0, 4.0] + [1e-4] * (n - 4))[None]
    return x, P


# --------------------------------------------------------------------------------------------
# (a) single updates, by hand
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("modified", [True, False])
def test_bearing_only_nis_is_the_wrapped_residual_squared_over_h_p_h_plus_r(modified):
    x, P = _prior()
    beta_hat = np.arctan2(3000.0, 4000.0)
    # h = [y, -x] / r^2 = [1.6e-4, -1.2e-4]: s = 1.6e-4^2 100^2 + 1.2e-4^2 200^2 + 0.01^2 = 9.32e-4
    s = 2.56e-4 + 5.76e-4 + 1e-4
    z = np.array([[beta_hat + 0.05, np.nan]])
    x_new, P_new, nis = nonlinear_update(x, P, z, False, BEARING_STD, RANGE_STD, modified, return_nis=True)
    assert nis.shape == (1,) and nis.dtype == np.float64
    assert nis[0] == pytest.approx(0.05**2 / s, rel=1e-12)                       # 2.682...
    # the state and covariance are those of the call without the NIS
    plain = nonlinear_update(x, P, z, False, BEARING_STD, RANGE_STD, modified)
    assert len(plain) == 2 and np.array_equal(plain[0], x_new) and np.array_equal(plain[1], P_new)


def test_bearing_only_nis_wraps_the_residual_across_south():
    """Prediction just west of due south (beta_hat = -pi + 0.0025), measurement just east of it
    (pi - 0.0075): the residual is -0.01 rad, not ~2 pi."""
    x, P = _prior()
    x[0, :2] = 4000.0 * np.array([np.sin(-np.pi + 0.0025), np.cos(-np.pi + 0.0025)])
    h = np.array([x[0, 1], -x[0, 0]]) / 4000.0**2
    s = h @ P[0, :2, :2] @ h + BEARING_STD**2
    z = np.array([[np.pi - 0.0075, np.nan]])
    nis = nonlinear_update(x, P, z, False, BEARING_STD, RANGE_STD, return_nis=True)[2]
    assert nis[0] == pytest.approx(0.01**2 / s, rel=1e-9)


@pytest.mark.parametrize("modified", [True, False])
def test_active_nis_uses_bearing_and_range_with_the_ekf_s(modified):
    """S = H P H' + R with H the EKF Jacobian (the MGEKF's g-rows change only P(k|k)), worked out:
    rows d beta = [1.6e-4, -1.2e-4], d r = [0.6, 0.8] over (x, y)."""
    x, P = _prior()
    beta_hat = np.arctan2(3000.0, 4000.0)
    s11 = 1.6e-4**2 * 100.0**2 + 1.2e-4**2 * 200.0**2 + BEARING_STD**2             # 9.32e-4
    s12 = 1.6e-4 * 0.6 * 100.0**2 - 1.2e-4 * 0.8 * 200.0**2                        # -2.88
    s22 = 0.6**2 * 100.0**2 + 0.8**2 * 200.0**2 + RANGE_STD**2                       # 29 300
    nu = np.array([0.02, 50.0])
    det = s11 * s22 - s12**2
    expected = (s22 * nu[0] ** 2 - 2.0 * s12 * nu[0] * nu[1] + s11 * nu[1] ** 2) / det
    z = np.array([[beta_hat + nu[0], 5000.0 + nu[1]]])
    x_new, P_new, nis = nonlinear_update(x, P, z, True, BEARING_STD, RANGE_STD, modified, return_nis=True)
    assert nis[0] == pytest.approx(expected, rel=1e-9)
    plain = nonlinear_update(x, P, z, True, BEARING_STD, RANGE_STD, modified)
    assert np.array_equal(plain[0], x_new) and np.array_equal(plain[1], P_new)


def test_converted_kf_nis_uses_its_cartesian_innovation_and_s():
    """z_c = r [sin b, cos b], R_c = J diag(s_b^2, s_r^2) J' at the measured values, S = P_xy + R_c."""
    x, P = _prior(4)
    beta, r = np.arctan2(3100.0, 3950.0), np.hypot(3100.0, 3950.0)
    converted = r * np.array([np.sin(beta), np.cos(beta)])                          # = (3100, 3950)
    J = np.array([[r * np.cos(beta), np.sin(beta)], [-r * np.sin(beta), np.cos(beta)]])
    S = P[0, :2, :2] + J @ np.diag([BEARING_STD**2, RANGE_STD**2]) @ J.T
    nu = converted - x[0, :2]
    x_new, P_new, nis = converted_update(x, P, np.array([[beta, r]]), BEARING_STD, RANGE_STD, return_nis=True)
    assert nis[0] == pytest.approx(nu @ np.linalg.inv(S) @ nu, rel=1e-9)
    plain = converted_update(x, P, np.array([[beta, r]]), BEARING_STD, RANGE_STD)
    assert np.array_equal(plain[0], x_new) and np.array_equal(plain[1], P_new)


def test_the_updates_give_each_run_its_own_nis():
    """Batched over runs: three runs in one call equal three one-run calls."""
    x, P = _prior()
    x3, P3 = np.repeat(x, 3, 0), np.repeat(P, 3, 0)
    x3[:, 0] += [0.0, 300.0, -500.0]
    z3 = np.array([[0.66, 5100.0], [0.70, 5050.0], [0.55, 4900.0]])
    for active in (False, True):
        batched = nonlinear_update(x3, P3, z3, active, BEARING_STD, RANGE_STD, return_nis=True)[2]
        single = [nonlinear_update(x3[i:i + 1], P3[i:i + 1], z3[i:i + 1], active, BEARING_STD, RANGE_STD,
                                   return_nis=True)[2][0] for i in range(3)]
        np.testing.assert_allclose(batched, single, rtol=1e-12)


# --------------------------------------------------------------------------------------------
# (b) model-matched Monte Carlo: the run-averaged NIS stays in its band
# --------------------------------------------------------------------------------------------

SIGMA_M, TAU, VELOCITY_STD = 0.01, 60.0, 15.0


def _model_matched_reports(runs: int = 200, scans: int = 300, passive=(60, 200), seed: int = 0,
                           bearing_std: float = np.radians(1.0), range_std: float = 10.0):
    """Truth drawn from the trackers' own model: x(k+1) = Phi x + Gamma u + w, w ~ N(0, Q) (Singer,
    tau 60 s, sigma_m 0.01 m/s^2), target velocity ~ N(0, 15^2) per axis and acceleration
    ~ N(0, sigma_m^2) at the start (the trackers' prior), own-ship zig-zag of +-0.05 m/s^2 east every
    40 s. Active (bearing + range) outside scans [passive[0], passive[1]), bearing only inside."""
    rng = np.random.default_rng(seed)
    time = np.arange(scans, dtype=float)
    active = (time < passive[0]) | (time >= passive[1])
    Phi, Gamma, Q = relative_motion_model(1.0, TAU, SIGMA_M)
    values, vectors = np.linalg.eigh(Q)
    Q_root = vectors * np.sqrt(np.clip(values, 0.0, None))                          # Q = Q_root Q_root'
    ownship_velocity0 = np.tile([0.0, 5.0], (runs, 1))
    u = np.zeros((runs, scans, 2))
    u[:, :, 0] = 0.05 * np.where((time // 40) % 2 == 0, 1.0, -1.0)
    x = np.zeros((runs, scans, 6))
    x[:, 0, :2] = [4000.0, 6000.0]
    x[:, 0, 2:4] = -ownship_velocity0 + VELOCITY_STD * rng.standard_normal((runs, 2))
    x[:, 0, 4:] = SIGMA_M * rng.standard_normal((runs, 2))
    for k in range(1, scans):
        x[:, k] = x[:, k - 1] @ Phi.T + u[:, k - 1] @ Gamma.T + rng.standard_normal((runs, 6)) @ Q_root.T
    beta, r = bearing_range(x[..., :2])
    z = np.stack([beta + bearing_std * rng.standard_normal((runs, scans)),
                  np.where(active, r + range_std * rng.standard_normal((runs, scans)), np.nan)], -1)
    return SonarReports(time, z, active, u, ownship_velocity0, bearing_std, range_std)


@pytest.fixture(scope="module")
def matched():
    return _model_matched_reports()


def _in_band(estimate) -> np.ndarray:
    band = nis_metrics(estimate.extras)
    return (band["nis"] >= band["nis_lower"]) & (band["nis"] <= band["nis_upper"])


TRACKERS = {"only MGEKF": OnlyMGEKF(sigma_m=SIGMA_M, tau=TAU, initial_velocity_std=VELOCITY_STD),
            "EKF": PlainEKF(sigma_m=SIGMA_M, tau=TAU, initial_velocity_std=VELOCITY_STD),
            "KF + MGEKF": KFPlusMGEKF(sigma_m=SIGMA_M, tau=TAU, initial_velocity_std=VELOCITY_STD,
                                      handover_acceleration_variance="consistent")}


@pytest.mark.parametrize("name", list(TRACKERS))
def test_run_exports_nis_and_its_dof_per_scan(matched, name):
    est = TRACKERS[name].run(matched)
    nis, dof = est.extras["nis"], est.extras["nis_dof"]
    assert nis.shape == dof.shape == (200, 300) and nis.dtype == dof.dtype == np.float64
    assert np.isnan(nis[:, 0]).all() and np.isnan(dof[:, 0]).all()           # the first scan starts the filter
    assert np.isfinite(nis[:, 1:]).all() and (nis[:, 1:] >= 0).all()
    np.testing.assert_array_equal(dof[:, 1:], np.where(matched.active[1:], 2.0, 1.0)[None].repeat(200, 0))


@pytest.mark.parametrize("name", list(TRACKERS))
def test_model_matched_run_average_nis_stays_in_its_95_percent_band(matched, name):
    """200 runs, 300 scans (active, passive 60-199, active): the run-averaged NIS is inside the 95 %
    band at >= 85 % of the steps, active and passive alike (measured: 93-94 % for each tracker with
    this seed, 92-97 % over seeds 0-7), and its mean over all runs and scans is the dof within 5 %.
    (KF + MGEKF's KF uses a white-acceleration model, not the truth's Singer one; close enough here.)"""
    est = TRACKERS[name].run(matched)
    inside = _in_band(est)[1:]
    active = matched.active[1:]
    assert inside.mean() >= 0.85, inside.mean()
    assert inside[active].mean() >= 0.85 and inside[~active].mean() >= 0.85, (inside[active].mean(),
                                                                               inside[~active].mean())
    nis = est.extras["nis"][:, 1:]
    assert np.mean(nis[:, active]) == pytest.approx(2.0, rel=0.05)
    assert np.mean(nis[:, ~active]) == pytest.approx(1.0, rel=0.05)


def test_a_filter_told_too_small_a_bearing_noise_leaves_the_band(matched):
    """The check has teeth: the same truth with the filter told sigma_beta / 3 (NIS ~ 9x on the
    bearing) is outside the band at most passive steps."""
    from dataclasses import replace

    told = replace(matched, bearing_std=matched.bearing_std / 3.0)
    inside = _in_band(TRACKERS["only MGEKF"].run(told))
    assert inside[~matched.active].mean() < 0.2


# --------------------------------------------------------------------------------------------
# (c) through the pipeline: experiment sonar_case1, 2 runs x 201 scans, with the recording
# --------------------------------------------------------------------------------------------

SHORT = ["scenario.duration=200", "mc.runs=2", "sensors.active_intervals=[[0,100]]", "record.runs=[1]"]


@pytest.fixture(scope="module")
def case1_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("sonar_nis")
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfg = compose("config", overrides=["experiment=sonar_case1", f"paths.artifacts={tmp}", *SHORT])
    ctx = RunContext(tmp / "runs" / "nis", tmp, list(SHORT))
    return run_experiment(cfg, ctx), ctx, list(cfg.filters)


def test_sonar_case1_metrics_have_nis_with_its_band_for_every_variant(case1_run):
    out, ctx, variants = case1_run
    assert variants == ["kf_mgekf", "kf_mgekf_consistent", "only_mgekf", "ekf"]
    metrics = pl.read_parquet(ctx.run_dir / "metrics.parquet")
    for key in variants:
        mine = metrics.filter(pl.col("variant_key") == key)
        for name in ("nis", "nis_lower", "nis_upper"):
            values = mine.filter(pl.col("series") == name).sort("step")["value"].to_numpy()
            assert values.size == 201, (key, name)
            assert np.isnan(values[0]) and np.isfinite(values[1:]).all(), (key, name)   # no update at scan 0
        band = {n: mine.filter(pl.col("series") == n).sort("step")["value"].to_numpy()[1:]
                for n in ("nis_lower", "nis_upper")}
        assert (band["nis_lower"] < band["nis_upper"]).all()
    summary = out.summary.filter(pl.col("series") == "nis")
    assert set(summary["variant_key"]) == set(variants)


def test_sonar_case1_recording_shows_nis_and_nees_with_their_bands(case1_run):
    from rerun.chunk import RrdReader

    _, ctx, variants = case1_run
    path = ctx.run_dir / "recording.rrd"
    entities = entity_index(read_chunks(path))
    for key in variants:
        for metric in ("nis", "nees"):
            # (KF + MGEKF's NEES is NaN while its 4-state KF runs; it has values once passive)
            for entity in (f"/metrics/{metric}/{key}", f"/metrics/{metric}/{key}_chi2_lower",
                           f"/metrics/{metric}/{key}_chi2_upper"):
                e = temporal(entities, entity, "Scalars:scalars")
                assert {"SeriesLines:names", "SeriesLines:colors", "SeriesLines:widths"} <= e["static"]
        assert temporal(entities, f"/metrics/nis/{key}", "Scalars:scalars")["rows"] == 200
    assert not any(p.startswith(("/metrics/nis_lower", "/metrics/nees_upper")) for p in entities)
    # the blueprint has a NIS and a NEES view on those entities
    reader = RrdReader(path)
    origins = {}
    for chunk in reader.stream(store=reader.blueprints()[0]).to_chunks():
        batch = chunk.to_record_batch()
        if "ViewBlueprint:space_origin" in batch.schema.names:
            for origin, name in zip(batch.column("ViewBlueprint:space_origin").to_pylist(),
                                    batch.column("ViewBlueprint:display_name").to_pylist()):
                origins[origin[0]] = name[0]
    assert origins["/metrics/nis"].startswith("NIS") and "95 % band" in origins["/metrics/nis"]
    assert origins["/metrics/nees"].startswith("NEES") and "95 % band" in origins["/metrics/nees"]
    # and the RMSE over the PCRLB of every variant, with its view
    for key in variants:
        temporal(entities, f"/metrics/position_rmse_over_bound/{key}", "Scalars:scalars")
    assert "PCRLB" in origins["/metrics/position_rmse_over_bound"]
