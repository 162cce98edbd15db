"""Stone Soup's particle filter vs ours on the same single-mode bootstrap SIR job (study 004's model).

Run from the repository root (needs the [stonesoup] extra):

    .venv/bin/python benchmarks/bench_stonesoup_pf.py [--particles 1000] [--repeats 5] [--runs 20]
                                                     [--target-sigma 0.05] [--buoys estimated|known] [--seed 1]

What is compared: one bootstrap SIR filter, written twice, on study 004 case 1 (conf/experiment/
sonobuoy_case1.yaml: the straight target, clean bearings: no misses, no clutter; 360 scans of 5 s;
the prior of the study: truth + N(0, P0) per run).

- The model: 20 states (the target and four drifting buoys, each x, y, vx, vy), every object CV with
  the process noise Gamma diag(sigma^2) Gamma' (Gamma's position gain T^2/2; the buoys' sigma the
  case's, the target's ``--target-sigma``: case 2's 0.05 m/s^2, since with case 1's 0.005 an
  unregularised SIR collapses onto a few particles, ours and Stone Soup's alike); 8 bearings per scan
  (the target from each buoy, each buoy from the observer), atan2(dx, dy) from north, Gaussian with
  the sensor's nominal std, residuals wrapped. ``--buoys known``: no buoy noise and the buoys' true
  start, so only the target is uncertain.
- Ours: filters.particle.MultipleModelParticleFilter restricted to that filter: auxiliary=False (the
  bootstrap SIR-MM), one mode (tpm = identity and max_acceleration = 0: every particle stays CV),
  lw_h = 0 (no Liu-West regularisation: Stone Soup's updater has none), systematic resampling every
  scan; both engines (the compiled scan, "numba", and the numpy loop), one run, one thread. It still
  does what the study needs besides (mode draws, the NIS, the ESS, mode probabilities), and its
  likelihood is float32.
- Stone Soup 1.9.1: ParticlePredictor with a LinearGaussianTimeInvariantTransitionModel (the same F
  and Q), ParticleUpdater with SystematicResampler (every scan) and a measurement model of the 8
  bearings (``BuoyBearings``, written here the way Stone Soup writes its own bearing models:
  vectorised over the particles, residuals wrapped through Bearing, scipy's multivariate normal
  log-density); one Detection and one SingleHypothesis per scan.
- The same start: Stone Soup gets our filter's initial cloud for that run (the same draws). After it,
  the random numbers differ (Stone Soup draws from numpy's global generator, seeded per run).
- The estimate: the weighted mean and covariance of the particles after the update, before
  resampling, in both (Stone Soup's updater returns the resampled cloud; a resampler wrapper keeps
  the weighted one it is handed).

What is timed (``time.perf_counter`` and this process's CPU time, filtering only): one run,
``--repeats`` times, the three alternating (a shared machine's load hits all alike); the medians. The
numba kernel is loaded (or compiled) once before. One BLAS thread (OPENBLAS_NUM_THREADS=1 unless set).

Checks (exit 1 when one fails; no timing assertion): the same likelihood (the start cloud's weights
for scan 1's bearings, ours and Stone Soup's, agree to float32 rounding: 1e-4 of the largest); the
same filter (``--runs`` runs through each, ours with numba: the position RMSE over each run, scans
1..360; the paired mean difference of the runs' RMSEs, Stone Soup - ours, within 3 sigma's coverage
of its standard error over the runs (Student's t with runs - 1 degrees of freedom) plus 2 % of the
RMSE: the two use different random numbers, so they agree only within Monte Carlo noise).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import statistics
import sys
import time
from pathlib import Path

# One BLAS thread unless the caller says otherwise (before numpy loads): the comparison is of one run
# on one thread, and OpenBLAS's threads on a 2-core machine shared with other jobs made Stone Soup's
# and our numpy loop's 20 x 3000 products several times slower (the compiled scan calls no BLAS)
for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_variable, "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


# the buoys' states known: no buoy noise in the truth or the filters (and, below, their true start
# with no spread as the prior)
KNOWN_BUOYS = ["scenario.buoy_sigma=0", "target_model.buoy_sigma=0"]


def reports_for(runs: int, seed: int, particles: int, buoys: str, target_sigma: float):
    from hydra import compose, initialize_config_dir

    from pipeline.run.config import build

    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        cfg = compose("config", overrides=["experiment=sonobuoy_case1", f"mc.runs={runs}",
                                           f"target_model.particles={particles}", f"target_model.target_sigma={target_sigma}"]
                      + (KNOWN_BUOYS if buoys == "known" else []))
    scenario, sensor, study = build(cfg.scenario, "scenario"), build(cfg.sensors, "sensors"), build(cfg.study, "study")
    truth = scenario.generate(runs, seed)
    reports = study.track_input(truth, sensor.measure(truth, seed), sensor, seed)
    if buoys == "known":
        prior_mean, prior_std = reports.prior_mean.copy(), reports.prior_std.copy()
        prior_mean[:, 4:], prior_std[4:] = truth.state[:, 0, 0, 4:], 0.0
        reports = dataclasses.replace(reports, prior_mean=prior_mean, prior_std=prior_std)
    if np.isnan(reports.z[:, 1:]).any() or reports.clutter_probability != 0:
        raise SystemExit("bench_stonesoup_pf: case 1's sensor should have no misses and no clutter")
    return cfg, truth, reports


def our_filter(cfg, engine: str):
    from filters.particle import MultipleModelParticleFilter

    model = cfg.target_model
    return MultipleModelParticleFilter(
        name="SIR", particles=int(model.particles), max_acceleration=0.0, target_sigma=float(model.target_sigma),
        buoy_sigma=float(model.buoy_sigma), tpm=np.eye(3).tolist(), lw_h=0.0, noise_gain=str(model.noise_gain),
        auxiliary=False, chunk_runs=1, workers=1, engine=engine)


def initial_cloud(estimator, reports) -> np.ndarray:
    """(N, 20) the start ``estimator`` draws for this one-run ``reports`` (its first numbers)."""
    (g,) = reports.generators(f"particles:{estimator.name}")
    return reports.prior_mean[0] + reports.prior_std * g.standard_normal((estimator.particles, 20))


class StoneSoupSIR:
    """The same filter from Stone Soup's components (built once; ``run`` filters one run)."""

    def __init__(self, cfg, reports) -> None:
        from stonesoup.base import Property
        from scipy.stats import multivariate_normal
        from stonesoup.models.measurement.nonlinear import NonLinearGaussianMeasurement
        from stonesoup.models.transition.linear import LinearGaussianTimeInvariantTransitionModel
        from stonesoup.predictor.particle import ParticlePredictor
        from stonesoup.resampler import Resampler
        from stonesoup.resampler.particle import SystematicResampler
        from stonesoup.types.angle import Bearing
        from stonesoup.types.array import StateVectors
        from stonesoup.updater.particle import ParticleUpdater

        from filters.particle.reference import BUOYS, _ModelParameters, cv_transition

        class BuoyBearings(NonLinearGaussianMeasurement):
            """Study 004's 8 bearings (seed eq 9): the target from each buoy, each buoy from the
            observer, atan2(dx, dy) from north, for every particle at once. Typed as Stone Soup's
            ``Bearing`` and wrapped to (-pi, pi] in the likelihood, as its own angle models do (their
            shared base class is private, so the three methods are written here)."""

            observer: np.ndarray = Property(doc="the fixed observer (east, north) [m]")

            @property
            def ndim_meas(self) -> int:
                return 2 * BUOYS

            def _bearings(self, state, noise=False, **kwargs):
                if isinstance(noise, bool) or noise is None:
                    noise = self.rvs(num_samples=state.state_vector.shape[1], **kwargs) if noise else 0
                x = np.asarray(state.state_vector, dtype=float)                       # (20, N)
                buoys = x[4:].reshape(BUOYS, 4, -1)[:, :2]                            # (4, 2, N)
                d_target = x[None, :2] - buoys
                d_buoy = buoys - np.asarray(self.observer, dtype=float)[None, :, None]
                bearings = np.concatenate([np.arctan2(d_target[:, 0], d_target[:, 1]),
                                           np.arctan2(d_buoy[:, 0], d_buoy[:, 1])])
                return StateVectors(bearings) + noise

            @staticmethod
            def _typed_vector():
                return np.array([[Bearing(0.0)]] * (2 * BUOYS))

            def function(self, state, noise=False, **kwargs):
                return self._typed_vector() + self._bearings(state, noise, **kwargs)

            def rvs(self, num_samples=1, **kwargs):
                return self._typed_vector() + super().rvs(num_samples, **kwargs)

            def logpdf(self, state1, state2, **kwargs):
                residual = state1.state_vector.astype(np.float64) - self._bearings(state2, **kwargs)
                for row in range(residual.shape[0]):        # each a bearing difference, wrapped
                    residual[row, :] = Bearing.mod_angle(residual[row, :])
                likelihood = np.atleast_1d(multivariate_normal.logpdf(residual.T, cov=self.covar(**kwargs)))
                return likelihood[0] if len(likelihood) == 1 else likelihood

        class KeepWeighted(Resampler):
            """SystematicResampler, keeping the weighted cloud it resamples (the estimate's)."""

            resampler: Resampler = Property(doc="the resampler")

            def resample(self, particles, nparts=None):
                self.weighted = particles
                return self.resampler.resample(particles, nparts)

        dt = np.diff(reports.time)
        if not np.allclose(dt, dt[0]):
            raise SystemExit("bench_stonesoup_pf: a time-invariant transition model needs a constant scan interval")
        self.dt = float(dt[0])
        model = cfg.target_model
        noise = _ModelParameters("Q", 0.0, float(model.target_sigma), float(model.buoy_sigma), str(model.noise_gain))
        transition = LinearGaussianTimeInvariantTransitionModel(
            transition_matrix=np.kron(np.eye(1 + BUOYS), cv_transition(self.dt)),
            covariance_matrix=noise._process_noise(self.dt))
        self.measurement_model = BuoyBearings(ndim_state=20, mapping=tuple(range(20)),
                                              noise_covar=np.diag(np.asarray(reports.std, dtype=float) ** 2),
                                              observer=np.asarray(reports.observer, dtype=float))
        self.resampler = KeepWeighted(resampler=SystematicResampler())
        self.predictor = ParticlePredictor(transition_model=transition)
        self.updater = ParticleUpdater(measurement_model=self.measurement_model, resampler=self.resampler)
        self.particles = int(model.particles)

    def run(self, reports, cloud: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """One run's (K, 20) estimates and (K, 20, 20) covariances from the (N, 20) start ``cloud``."""
        from stonesoup.types.angle import Bearing
        from stonesoup.types.array import StateVector, StateVectors
        from stonesoup.types.detection import Detection
        from stonesoup.types.hypothesis import SingleHypothesis
        from stonesoup.types.state import ParticleState

        np.random.seed(seed)             # Stone Soup's process noise and resampling offsets: numpy's global generator
        start = datetime.datetime(2000, 1, 1)
        K = reports.time.size
        N = cloud.shape[0]
        states, covariances = np.full((K, 20), np.nan), np.full((K, 20, 20), np.nan)
        state = ParticleState(StateVectors(cloud.T.copy()), log_weight=np.full(N, -np.log(N)), timestamp=start)
        states[0], covariances[0] = np.asarray(state.mean, dtype=float).ravel(), state.covar
        for k in range(1, K):
            when = start + datetime.timedelta(seconds=float(reports.time[k] - reports.time[0]))
            detection = Detection(StateVector([Bearing(b) for b in reports.z[0, k]]), timestamp=when,
                                  measurement_model=self.measurement_model)
            prediction = self.predictor.predict(state, timestamp=when)
            state = self.updater.update(SingleHypothesis(prediction, detection))
            weighted = self.resampler.weighted
            states[k], covariances[k] = np.asarray(weighted.mean, dtype=float).ravel(), weighted.covar
        return states, covariances


def weights_agree(stonesoup: StoneSoupSIR, reports, cloud: np.ndarray, k: int = 1) -> float:
    """The largest difference of the normalised weights that our likelihood (float32, as the filters
    evaluate it) and Stone Soup's measurement model give the cloud ``cloud`` (N, 20) for scan k's
    bearings, relative to the largest weight: the same likelihood up to float32 rounding."""
    from stonesoup.types.angle import Bearing
    from stonesoup.types.array import StateVector, StateVectors
    from stonesoup.types.detection import Detection
    from stonesoup.types.state import ParticleState

    from filters.particle import SonobuoyModel

    model = SonobuoyModel(0.0, 0.0, 0.0, "standard", reports.likelihood(), np.asarray(reports.observer, dtype=float))
    ours = model.log_likelihood(cloud[None], reports.z[:1, k])[0]
    detection = Detection(StateVector([Bearing(b) for b in reports.z[0, k]]),
                          measurement_model=stonesoup.measurement_model)
    theirs = np.asarray(stonesoup.measurement_model.logpdf(detection, ParticleState(StateVectors(cloud.T.copy()))),
                        dtype=float)
    w_ours, w_theirs = (np.exp(v - v.max()) for v in (ours, theirs))
    w_ours, w_theirs = w_ours / w_ours.sum(), w_theirs / w_theirs.sum()
    return float(np.abs(w_ours - w_theirs).max() / w_theirs.max())


def position_rmse(states: np.ndarray, truth_states: np.ndarray) -> float:
    """RMS over scans 1..K-1 of the target position error [m] (states (K, 20), truth (K, 20))."""
    error = np.linalg.norm(states[1:, :2] - truth_states[1:, :2], axis=-1)
    return float(np.sqrt(np.mean(error**2)))


def main(argv=None) -> int:
    from benchmarks.results_file import Column, Table, add_results_argument, start, write_result

    context = start("benchmarks/bench_stonesoup_pf.py", argv)
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--particles", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=5, help="timed single-run filterings per filter (median)")
    parser.add_argument("--runs", type=int, default=20, help="runs filtered by each for the accuracy check")
    parser.add_argument("--timed-run", type=int, default=0, help="which run is timed")
    parser.add_argument("--buoys", choices=("estimated", "known"), default="estimated",
                        help="estimated: study 004's 20 states as they are (buoys drifting with noise, their start "
                             "uncertain); known: no buoy noise, the buoys' true start with no spread")
    parser.add_argument("--target-sigma", type=float, default=0.05,
                        help="the filters' target process-noise std [m/s^2]: case 2's 0.05 (with case 1's 0.005 "
                             "the unregularised SIR collapses onto a few particles, in both)")
    parser.add_argument("--seed", type=int, default=1)
    add_results_argument(parser)
    args = parser.parse_args(argv)
    if args.particles < 10 or args.repeats < 1 or args.runs < 2 or not 0 <= args.timed_run < args.runs:
        parser.error("--particles >= 10, --repeats >= 1, --runs >= 2, 0 <= --timed-run < --runs")

    cfg, truth, reports = reports_for(args.runs, args.seed, args.particles, args.buoys, args.target_sigma)
    K = reports.z.shape[1]
    ours = {engine: our_filter(cfg, engine) for engine in ("numba", "numpy")}
    stonesoup = StoneSoupSIR(cfg, reports)
    print(f"study 004 case 1, one-mode bootstrap SIR, buoys {args.buoys}, target sigma {args.target_sigma} m/s^2: "
          f"{args.particles} particles x {K - 1} scans x 20 states, 8 bearings per scan; "
          f"{len(os.sched_getaffinity(0))} processors, load average {os.getloadavg()[0]:.1f}, "
          f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}")

    one = reports.select([args.timed_run])
    started = time.perf_counter()
    ours["numba"].run(one)
    print(f"numba kernel ready (cache load or compilation) in {time.perf_counter() - started:.2f} s")
    cloud = initial_cloud(ours["numba"], one)
    weights = weights_agree(stonesoup, one, cloud)
    print(f"the same likelihood: scan 1's weights of the start cloud, ours vs Stone Soup's, differ by at most "
          f"{weights:.1e} of the largest")
    contestants = {"ours, numba": lambda: ours["numba"].run(one),
                   "ours, numpy": lambda: ours["numpy"].run(one),
                   "Stone Soup": lambda: stonesoup.run(one, cloud, args.seed * 100_003 + args.timed_run)}
    seconds = {name: [] for name in contestants}
    cpu = {name: [] for name in contestants}
    for i in range(args.repeats):
        order = list(contestants) if i % 2 == 0 else list(contestants)[::-1]
        for name in order:
            started, started_cpu = time.perf_counter(), time.process_time()
            contestants[name]()
            seconds[name].append(time.perf_counter() - started)
            cpu[name].append(time.process_time() - started_cpu)
    medians = {name: statistics.median(s) for name, s in seconds.items()}
    cpu_medians = {name: statistics.median(s) for name, s in cpu.items()}
    print(f"filtering one run (median of {args.repeats}, alternating; cpu: this process's CPU time, less "
          f"sensitive to other processes on the machine):")
    for name, s in seconds.items():
        print(f"  {name:12s} {medians[name]:8.3f} s  ({1e6 * medians[name] / (K - 1):6.0f} us/scan)  cpu "
              f"{cpu_medians[name]:7.3f} s   runs: {', '.join(f'{x:.3f}' for x in s)}")
    for name in ("ours, numba", "ours, numpy"):
        print(f"  Stone Soup / {name}: {medians['Stone Soup'] / medians[name]:.1f}x wall, "
              f"{cpu_medians['Stone Soup'] / cpu_medians[name]:.1f}x cpu")

    # accuracy: the same runs through ours (numba) and Stone Soup, paired by run
    started = time.perf_counter()
    batched = our_filter(cfg, "numba")
    batched.workers = None                 # the runs in parallel (the results do not depend on it)
    estimate = batched.run(reports)
    true = truth.state[:, :, 0]
    mine = np.array([position_rmse(estimate.state[r], true[r]) for r in range(args.runs)])
    theirs = np.empty(args.runs)
    for r in range(args.runs):
        single = reports.select([r])
        states, _ = stonesoup.run(single, initial_cloud(ours["numba"], single), args.seed * 100_003 + r)
        theirs[r] = position_rmse(states, true[r])
    difference = theirs - mine
    mean, se = float(difference.mean()), float(difference.std(ddof=1) / np.sqrt(args.runs))
    # 3 sigma's coverage (99.73 %) from Student's t with runs - 1 degrees of freedom: with a few runs the
    # standard error is itself uncertain, and a normal 3 SE failed a 4-run check on a fair stream
    from scipy.stats import t as student_t
    multiplier = float(student_t.ppf(1 - 0.0027 / 2, args.runs - 1))
    tolerance = multiplier * se + 0.02 * float(np.mean(mine))
    ok = bool(abs(mean) <= tolerance) and weights < 1e-4
    print(f"accuracy over {args.runs} runs ({time.perf_counter() - started:.0f} s): position RMSE per run, mean "
          f"{mine.mean():.1f} m ours, {theirs.mean():.1f} m Stone Soup (medians {np.median(mine):.1f}, "
          f"{np.median(theirs):.1f}); paired difference {mean:+.1f} m, standard error {se:.1f} m "
          f"(|difference| <= {multiplier:.2f} SE + 2 % = {tolerance:.1f} m: {'OK' if ok else 'FAILED'})")
    rows = [{"filter": name, "wall": medians[name], "cpu": cpu_medians[name],
             "vs_compiled": medians[name] / medians["ours, numba"],
             "cpu_vs_compiled": cpu_medians[name] / cpu_medians["ours, numba"],
             "per_scan_us": 1e6 * medians[name] / (K - 1)} for name in contestants]
    columns = [Column("filter", "filter"), Column("wall", "one run", "seconds", ".3f"),
               Column("vs_compiled", "vs ours compiled", "ratio", ".1f"), Column("cpu", "CPU", "seconds", ".3f"),
               Column("cpu_vs_compiled", "CPU vs ours compiled", "ratio", ".1f")]
    write_result("stonesoup_pf", "Stone Soup's particle filter against ours: one-mode bootstrap SIR (filtering only)",
                 [Table(columns, rows)],
                 [f"One run, one thread, median of {args.repeats} with the three alternating; CPU: this process's CPU "
                  "time, less sensitive to other processes on the machine.",
                  f"The same likelihood: scan 1's weights of the start cloud differ by at most {weights:.1e} of the "
                  "largest (ours float32).",
                  f"The same filter over {args.runs} runs: position RMSE mean {mine.mean():.1f} m ours, "
                  f"{theirs.mean():.1f} m Stone Soup; paired difference {mean:+.1f} m, standard error {se:.1f} m "
                  f"(tolerance {tolerance:.1f} m): {'OK' if ok else 'FAILED'}."],
                 context=context, parameters={"particles": args.particles, "scans": K - 1, "buoys": args.buoys,
                                              "target sigma [m/s^2]": args.target_sigma,
                                              "accuracy runs": args.runs, "seed": args.seed},
                 directory=args.results_dir)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
