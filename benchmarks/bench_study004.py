"""Study 004 benchmark: the AMMPF (regularised) on case 2, 100 runs x 1000 particles x 360 scans.

    python benchmarks/bench_study004.py [--runs 100] [--single-runs 5] [--seed 1]

Times the batched filter (runs in chunks, two threads) on all runs, and the same filter one run at
a time (R = 1 batches, one thread) on ``--single-runs`` runs, extrapolated per run; checks that a
run filtered alone gives exactly the batched run's estimate (per-run random streams).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hydra import compose, initialize_config_dir  # noqa: E402

from pipeline.config import build  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--single-runs", type=int, default=5, help="runs also filtered one at a time (0: none)")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    if args.runs < 1 or args.single_runs < 0:
        parser.error(f"--runs {args.runs} must be >= 1 and --single-runs {args.single_runs} >= 0")
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        cfg = compose("config", overrides=["experiment=sonobuoy_case2", f"mc.runs={args.runs}"])
    scenario, sensor, study = build(cfg.scenario, "scenario"), build(cfg.sensors, "sensors"), build(cfg.study, "study")
    truth = scenario.generate(args.runs, args.seed)
    reports = study.track_input(truth, sensor.measure(truth, args.seed), sensor, args.seed)
    ammpf = build(cfg.filters.ammpf, "filters.ammpf")
    print(f"study 004 case 2, AMMPF (lw_h {ammpf.lw_h}), {ammpf.particles} particles, {reports.z.shape[1] - 1} scans; "
          f"{os.cpu_count()} processors")

    started = time.perf_counter()
    batched = ammpf.run(reports)
    batched_seconds = time.perf_counter() - started
    final = np.linalg.norm(batched.state[:, -1, :2] - truth.state[:, -1, 0, :2], axis=-1)
    print(f"batched, {args.runs} runs:            {batched_seconds:7.1f} s  "
          f"(final RMSE {np.sqrt(np.mean(final**2)):.0f} m, loss {np.mean(final > 2000):.0%})")

    if args.single_runs == 0:                  # the batched figure only
        return 0
    single = build(cfg.filters.ammpf, "filters.ammpf")
    single.workers, single.chunk_runs = 1, 1
    started = time.perf_counter()
    equal = True
    for r in range(args.single_runs):
        alone = single.run(reports.select([r]))
        equal &= bool(np.array_equal(alone.state[0], batched.state[r]))
    per_run = (time.perf_counter() - started) / args.single_runs
    print(f"one run at a time, {args.single_runs} runs: {per_run:7.2f} s per run -> "
          f"{per_run * args.runs:.1f} s for {args.runs} runs (extrapolated); batched is "
          f"{per_run * args.runs / batched_seconds:.1f}x faster")
    print(f"a run filtered alone equals the batched run exactly: {equal}")
    return 0 if equal else 1


if __name__ == "__main__":
    sys.exit(main())
