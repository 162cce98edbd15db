"""Study 002 compute benchmark: batched local / proposed / EXX bias registration vs the obvious-way loop.

Run from the repository root:

    .venv/bin/python benchmarks/bench_study002.py --runs 100 --loop-runs 2 --repeat 3 --seed 1

Inputs are built exactly as the experiment builds them: the Hydra config ``experiment=async_bias``
composed from ``conf/``, scenario / sensors / study / filters instantiated with
``pipeline.run.config.build``, then ``truth = scenario.generate(R, seed)``,
``detections = sensor.measure(truth, seed)``, ``reports = study.track_input(truth, detections,
sensor, seed)`` (32 targets, 200 s, 400 reports of two radars).

What is timed (``time.perf_counter``; estimation only, no data generation):

- the batched variants of ``filters/bias/reference.py`` as configured (``filters.local``, ``.proposed``,
  ``.exx``: output targets 1 and 32), all ``--runs`` runs in one ``.run`` call, median of
  ``--repeat`` calls, each with both engines: the compiled local-filter steps (``engine: numba``,
  the default; filters/bias/kernel.py, loaded before the clock) and the numpy steps
  (``engine: numpy``, the reference);
- the reference loop of the proposed method (``benchmarks/reference_bias.py``: one run, one
  report, one target at a time, covariance-form recursion) on the first ``--loop-runs`` runs,
  once; its time for ``--runs`` runs is extrapolated linearly from its per-run time.

Equality check (the script exits 1 if it fails; there are no timing assertions), on the loop
runs: the batched proposed method vs the reference loop,

- bias estimates after every report: max |difference| / prior std, over the 8 components;
- the compensated tracks X^b - G beta_hat_i of the reporting radar after every report: max
  |difference| in metres (and relative to max |value|), once for the timed result (targets 1 and
  32, sliced from the batch of ``--runs`` runs) and once for every target (a batched instance with
  output_targets=null, run on the loop runs only, untimed);
- also (informational) the biased local tracks and the bias covariance (relative to the prior
  variances).

The batched code keeps the least squares in an information form normalised by the prior std;
the reference uses the seed's covariance recursion (eqs 33-35). They are equal in exact
arithmetic; tolerance here 1e-8 (bias, in prior std) and 1e-8 m (tracks).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from hydra import compose, initialize_config_dir  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from benchmarks.reference_bias import reference_pseudo_bias  # noqa: E402
from benchmarks.results_file import Column, Table, add_results_argument, start, write_result  # noqa: E402
from filters.bias import RadarReports, TrackStart  # noqa: E402
from pipeline.run.config import build  # noqa: E402

BIAS_TOL = 1e-8      # max |d bias| / prior std
TRACK_TOL = 1e-8     # max |d compensated track| [m]
VARIANTS = ("local", "proposed", "exx")


# ---------------------------------------------------------------------------------------------
# inputs
# ---------------------------------------------------------------------------------------------
def compose_config(*overrides: str):
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        return compose("config", overrides=["experiment=async_bias", *overrides])


def build_inputs(cfg, runs: int, seed: int):
    """(estimators by key, reports) exactly as pipeline.run.runner builds them."""
    study = build(cfg.study, "study")
    scenario = build(cfg.scenario, "scenario")
    sensor = build(cfg.sensors, "sensors")
    estimators = {v: build(cfg.filters[v], f"filters.{v}") for v in VARIANTS}
    study.check(scenario, sensor, estimators)
    truth = scenario.generate(runs, seed)
    detections = sensor.measure(truth, seed)
    reports = study.track_input(truth, detections, sensor, seed)
    return estimators, reports


def first_runs(reports: RadarReports, runs: int) -> RadarReports:
    start = reports.start
    return RadarReports(reports.time, reports.sensor, reports.z[:runs], reports.sensor_position, reports.noise_std,
                        TrackStart(start.time, start.state[:runs], start.covariance))


# ---------------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    context = start("benchmarks/bench_study002.py", argv)
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=100, help="Monte Carlo runs for the batched variants")
    parser.add_argument("--loop-runs", type=int, default=2, help="runs for the reference loop (extrapolated)")
    parser.add_argument("--repeat", type=int, default=3, help="batched calls per variant (median reported)")
    parser.add_argument("--seed", type=int, default=1)
    add_results_argument(parser)
    args = parser.parse_args(argv)
    runs, repeat = args.runs, args.repeat
    loop_runs = min(args.loop_runs, runs)
    if runs < 1 or loop_runs < 1 or repeat < 1:
        parser.error("--runs, --loop-runs and --repeat must be >= 1")

    cfg = compose_config()
    estimators, reports = build_inputs(cfg, runs, args.seed)
    R, K, T, _ = reports.z.shape
    S = reports.sensors
    print(f"Study 002 benchmark: experiment=async_bias, {T} targets, {S} radars, {K} reports "
          f"({reports.time[0]:g}..{reports.time[-1]:g} s), {runs} runs, seed {args.seed}")

    # ---- batched variants ----------------------------------------------------------------------
    from filters.bias import kernel as bias_kernel
    bias_kernel.warm_up()                          # numba's start and the kernels' load before any clock
    rows = []
    results = {}
    numpy_results = {}
    for key in VARIANTS:
        for engine in ("numba", "numpy"):
            est = estimators[key] if engine == "numba" else build(OmegaConf.merge(cfg.filters[key], {"engine": engine}),
                                                                 f"filters.{key}")
            times = []
            for _ in range(repeat):
                t0 = time.perf_counter()
                (results if engine == "numba" else numpy_results)[key] = est.run(reports)
                times.append(time.perf_counter() - t0)
            seconds = statistics.median(times)
            label = "compiled steps" if engine == "numba" else "numpy steps"
            rows.append({"name": f"{est.name}, batched, {label}", "runs": runs, "seconds": seconds,
                         "per_run": seconds / runs, "at_runs": seconds, "extrapolated": False,
                         "variant": key, "engine": engine})
            print(f"  {key} ({engine}): median {seconds:.3f} s of {[round(t, 3) for t in times]}", file=sys.stderr,
                  flush=True)

    # ---- reference loop (proposed) -------------------------------------------------------------
    proposed = estimators["proposed"]
    q = proposed.process_noise_density
    prior_std = proposed.prior_std
    loop_seconds = 0.0
    refs = []
    for r in range(loop_runs):
        t0 = time.perf_counter()
        refs.append(reference_pseudo_bias(reports, runs=[r], q=q, prior_std=prior_std))
        loop_seconds += time.perf_counter() - t0
        print(f"  reference loop: {r + 1}/{loop_runs} runs, {loop_seconds:.1f} s", file=sys.stderr, flush=True)
    ref_bias = np.concatenate([x.bias for x in refs])
    ref_bias_cov = np.concatenate([x.bias_covariance for x in refs])
    ref_track = np.concatenate([x.track_state for x in refs])
    ref_comp = np.concatenate([x.compensated_state for x in refs])
    per_run = loop_seconds / loop_runs
    rows.append({"name": "proposed, reference loop", "runs": loop_runs, "seconds": loop_seconds,
                 "per_run": per_run, "at_runs": per_run * runs, "extrapolated": loop_runs < runs})

    # ---- equality ------------------------------------------------------------------------------
    scale = np.tile(prior_std, S)
    L = loop_runs
    timed = results["proposed"]
    sel = timed.targets
    checks = []

    def track_check(label, state, reference):
        d = np.abs(state - reference)
        checks.append({"what": label, "max_abs": float(d.max()), "unit": "m",
                       "rel": float(d.max() / np.abs(reference).max()), "tol": TRACK_TOL,
                       "passed": bool(np.isfinite(d).all() and d.max() < TRACK_TOL)})

    d_bias = np.abs(timed.bias[:L] - ref_bias) / scale
    checks.append({"what": f"bias estimate, {K} reports x {4 * S} components (|d| / prior std)",
                   "max_abs": float(d_bias.max()), "unit": "prior std",
                   "rel": float(d_bias.max()), "tol": BIAS_TOL,
                   "passed": bool(np.isfinite(d_bias).all() and d_bias.max() < BIAS_TOL)})
    track_check(f"compensated tracks, timed result (targets {', '.join(str(t + 1) for t in sel)})",
                timed.compensated_state[:L], ref_comp[:, :, sel])
    all_targets = build(OmegaConf.merge(cfg.filters.proposed, {"output_targets": None}), "filters.proposed")
    full = all_targets.run(first_runs(reports, L))
    track_check(f"compensated tracks, all {T} targets", full.compensated_state, ref_comp)
    d_track = np.abs(full.track_state - ref_track)
    d_cov = np.abs(full.bias_covariance - ref_bias_cov) / (scale[:, None] * scale[None, :])
    d_bias_full = np.abs(full.bias - ref_bias) / scale

    # ---- report --------------------------------------------------------------------------------
    print()
    print(f"Equality, batched proposed vs reference loop ({L} runs, every report):")
    for c in checks:
        verdict = "PASS" if c["passed"] else "FAIL"
        if c["unit"] == "m":
            print(f"  [{verdict}] {c['what']}: max|d| = {c['max_abs']:.2e} m (rel to max|x| {c['rel']:.1e}; "
                  f"tol {c['tol']:g} m)")
        else:
            print(f"  [{verdict}] {c['what']}: max = {c['max_abs']:.2e} (tol {c['tol']:g})")
    print(f"  [info] all-targets instance: bias max|d|/prior std = {d_bias_full.max():.2e}; biased local tracks "
          f"max|d| = {d_track.max():.2e} m; bias covariance max|d|/(prior std_a prior std_b) = {d_cov.max():.2e}")
    for key in VARIANTS:
        a, b = results[key], numpy_results[key]
        d_engines = max(float(np.nanmax(np.abs(a.compensated_state - b.compensated_state))),
                        float(np.nanmax(np.abs(np.nan_to_num(a.bias - b.bias)) / scale)))
        print(f"  [info] {key}: compiled vs numpy steps, all {runs} runs: max |d| of the compensated tracks [m] and "
              f"of the bias [prior std] = {d_engines:.2e}")

    print()
    base = rows[-1]["at_runs"]
    print(f"| implementation | runs timed | seconds | s/run | s for {runs} runs | speed-up vs loop |")
    print("|---|---:|---:|---:|---:|---:|")
    for r in rows:
        star = "*" if r["extrapolated"] else ""
        speed = f"{base / r['at_runs']:.1f}x"
        print(f"| {r['name']} | {r['runs']} | {r['seconds']:.3f} | {r['per_run']:.4f} | {r['at_runs']:.2f}{star} "
              f"| {speed} |")
    notes = [f"Batched: one .run over all {runs} runs, median of {repeat}. Reference loop: one run at a time, "
             f"summed, timed once."]
    if loop_runs < runs:
        notes.append(f"* extrapolated, not measured: the loop's measured per-run time x {runs} runs.")
    notes.append("The reference loop implements the proposed method only; its speed-up column compares each "
                 "batched variant with the loop of the proposed method (for local and EXX: context, not a "
                 "like-for-like comparison).")
    for n in notes:
        print(n)
    threads = {k: os.environ[k] for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
               if k in os.environ}
    print(f"Machine: {platform.platform()}, {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
          f"Python {platform.python_version()}, numpy {np.__version__}"
          + (f", {threads}" if threads else ""))
    compiled = {r["variant"]: r["at_runs"] for r in rows if r.get("engine") == "numba"}
    table_rows = [{**r, "timed": f"{r['runs']}" + (" (extrapolated)" if r["extrapolated"] else ""),
                   "vs_loop": base / r["at_runs"],
                   "numpy_over_compiled": r["at_runs"] / compiled[r["variant"]] if r.get("engine") == "numpy" else None}
                  for r in rows]
    columns = [Column("name", "implementation"), Column("timed", "runs timed"),
               Column("at_runs", f"{runs} runs", "seconds", ".3f"),
               Column("vs_loop", "vs reference loop (proposed)", "ratio", ".1f"),
               Column("numpy_over_compiled", "numpy / compiled steps", "ratio", ".2f")]
    check_notes = [f"{'PASS' if c['passed'] else 'FAIL'}: {c['what']}: max {c['max_abs']:.2e} {c['unit']} "
                   f"(tolerance {c['tol']:g})" for c in checks]
    write_result("study002", "Study 002: batched bias registration against the one-run-one-target loop (estimation only)",
                 [Table(columns, table_rows)], notes + check_notes, context=context,
                 parameters={"experiment": "async_bias", "runs": runs, "reference-loop runs": loop_runs,
                             "targets": T, "radars": S, "reports": K, "seed": args.seed},
                 directory=args.results_dir)
    return 0 if all(c["passed"] for c in checks) else 1


if __name__ == "__main__":
    sys.exit(main())
