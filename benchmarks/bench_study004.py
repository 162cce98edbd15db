"""Study 004 benchmark: the regularised AMMPF (and the SIR-MM) on case 2 (100 runs x 1000 particles x
360 scans) or case 1B (3000 particles), the compiled scan (engine "numba") beside the numpy loop
(engine "numpy", the code before it) in the same run.

    python benchmarks/bench_study004.py [--case 2|1b] [--runs 100] [--repeats 3] [--variants ammpf,sir_mm]
                                        [--engines numba,numpy] [--single-runs 5] [--processes N] [--seed 1]

Filtering only: each variant and engine filters the same reports ``--repeats`` times, the engines
alternating (a shared machine's load hits both alike); the median is printed with the spread.
Whole processes (``--processes N``): this script run again as a fresh process per engine, N times
alternating, timed from outside: Python start, imports, the configuration, the simulation, the
compiled kernel's load from numba's cache (or its compilation) and the filtering. ``--jit`` times
the first process with an empty numba cache (the one-off compilation) and the next one with it.
``--single-runs``: the same filter one run at a time on that many runs, checking that a run
filtered alone equals the batched run exactly (per-run random streams).
The limits behind these numbers: benchmarks/particle_limits.md.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.results_file import Column, Table, add_results_argument, start, write_result  # noqa: E402

EXPERIMENTS = {"2": "sonobuoy_case2", "1b": "sonobuoy_case1b"}
REPEATS = 3


def reports_for(case: str, runs: int, seed: int):
    from hydra import compose, initialize_config_dir

    from pipeline.run.config import build

    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        cfg = compose("config", overrides=[f"experiment={EXPERIMENTS[case]}", f"mc.runs={runs}"])
    scenario, sensor, study = build(cfg.scenario, "scenario"), build(cfg.sensors, "sensors"), build(cfg.study, "study")
    truth = scenario.generate(runs, seed)
    reports = study.track_input(truth, sensor.measure(truth, seed), sensor, seed)
    return cfg, truth, reports


def make_filter(cfg, key: str, engine: str):
    """The experiment's filter ``key``; "sir_mm" where the experiment has none (case 1B) is its AMMPF
    made the bootstrap SIR-MM (as conf/filter/sir_mm.yaml)."""
    from pipeline.run.config import build

    estimator = build(cfg.filters[key if key in cfg.filters else "ammpf"], f"filters.{key}")
    if key not in cfg.filters:
        estimator.name, estimator.auxiliary = "SIR-MM", False
    estimator.engine = engine
    return estimator


def final_rmse(estimate, truth) -> tuple[float, float]:
    final = np.linalg.norm(estimate.state[:, -1, :2] - truth.state[:, -1, 0, :2], axis=-1)
    return float(np.sqrt(np.mean(final**2))), float(np.mean(final > 2000))


def filtering(args) -> int:
    cfg, truth, reports = reports_for(args.case, args.runs, args.seed)
    engines, variants = args.engines.split(","), args.variants.split(",")
    print(f"study 004 case {args.case}: {args.runs} runs x {cfg.target_model.particles} particles x "
          f"{reports.z.shape[1] - 1} scans; {len(os.sched_getaffinity(0))} processors, load average "
          f"{os.getloadavg()[0]:.1f}")
    if "numba" in engines:                            # the compiled kernel's load (or compilation), once
        started = time.perf_counter()
        make_filter(cfg, variants[0], "numba").run(reports.select([0]))
        print(f"numba kernel ready (cache load or compilation) in {time.perf_counter() - started:.2f} s")
    medians, rows = {}, []
    for key in variants:
        seconds = {engine: [] for engine in engines}
        result = {}
        for _ in range(args.repeats):
            for engine in engines:                    # alternating: the same load for both
                estimator = make_filter(cfg, key, engine)
                started = time.perf_counter()
                result[engine] = estimator.run(reports)
                seconds[engine].append(time.perf_counter() - started)
        row = {"variant": key}
        for engine in engines:
            medians[key, engine] = statistics.median(seconds[engine])
            rmse, loss = final_rmse(result[engine], truth)
            row.update({engine: medians[key, engine], f"{engine}_rmse": rmse, f"{engine}_loss": 100 * loss})
            print(f"{key:7s} {engine:6s} filtering only: median {medians[key, engine]:7.2f} s of {args.repeats} "
                  f"({', '.join(f'{s:.2f}' for s in seconds[engine])})  final RMSE {rmse:.0f} m, loss {loss:.0%}")
        if len(engines) == 2:
            print(f"{key:7s} {engines[1]} / {engines[0]}: {medians[key, engines[1]] / medians[key, engines[0]]:.1f}x")
        if {"numba", "numpy"} <= set(engines):
            row["ratio"] = row["numpy"] / row["numba"]
        rows.append(row)
    record(args, "", rows, [f"Filtering only: median of {args.repeats}, the engines alternating (a shared machine's "
                            "load hits both alike); the kernel loaded before the clock.",
                            "Final RMSE: position error at the last scan; loss: share of runs ending over 2 km off."],
           {"particles": int(cfg.target_model.particles), "scans": reports.z.shape[1] - 1,
            "repeats": f"{args.repeats}" + ("" if args.repeats == REPEATS else f" (the default is {REPEATS})")})
    if args.single_runs:
        return single_runs(args, cfg, reports, variants[0], engines[0])
    return 0


def record(args, suffix: str, rows: list[dict], notes: list[str], size: dict) -> None:
    """The results file of this case (``suffix``: ``""`` filtering only, ``"_processes"`` whole processes);
    not written with one engine, which has no ratio partner."""
    if "ratio" not in rows[0]:
        print("results not recorded: the ratio needs both engines (--engines numba,numpy)")
        return
    columns = [Column("variant", "variant"), Column("numba", "compiled", "seconds", ".2f"),
               Column("numpy", "numpy loop", "seconds", ".2f"), Column("ratio", "numpy / compiled", "ratio", ".1f")]
    if "numba_rmse" in rows[0]:
        columns += [Column("numba_rmse", "final RMSE, compiled [m]", "number", ".0f"),
                    Column("numpy_rmse", "numpy [m]", "number", ".0f"),
                    Column("numba_loss", "loss, compiled [% of runs]", "number", ".0f"),
                    Column("numpy_loss", "numpy [% of runs]", "number", ".0f")]
    what = "whole processes, timed from outside" if suffix else "filtering only"
    write_result(f"study004_case{args.case}{suffix}", f"Study 004 case {args.case.upper()}: the particle filters, "
                 f"compiled scan against the numpy loop ({what})", [Table(columns, rows)], notes, context=args.context,
                 parameters={"experiment": EXPERIMENTS[args.case], "runs": args.runs, **size, "seed": args.seed},
                 directory=args.results_dir)


def single_runs(args, cfg, reports, key: str, engine: str) -> int:
    batched = make_filter(cfg, key, engine).run(reports)
    single = make_filter(cfg, key, engine)
    single.workers, single.chunk_runs = 1, 1
    started = time.perf_counter()
    equal = True
    for r in range(min(args.single_runs, args.runs)):
        alone = single.run(reports.select([r]))
        equal &= bool(np.array_equal(alone.state[0], batched.state[r]))
    per_run = (time.perf_counter() - started) / min(args.single_runs, args.runs)
    print(f"{key} {engine}, one run at a time: {per_run:.2f} s per run (one thread)")
    print(f"a run filtered alone equals the batched run exactly: {equal}")
    return 0 if equal else 1


def processes(args) -> int:
    """Whole processes, timed from outside, engines alternating."""
    engines = args.engines.split(",")
    base = [sys.executable, str(Path(__file__).resolve()), "--case", args.case, "--runs", str(args.runs),
            "--variants", args.variants.split(",")[0], "--repeats", "1", "--single-runs", "0", "--seed", str(args.seed),
            "--quiet"]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    if args.jit:
        with tempfile.TemporaryDirectory() as cache:
            for label in ("empty numba cache (compiles)", "numba cache filled by it"):
                started = time.perf_counter()
                subprocess.run(base + ["--engines", "numba"], check=True, env=dict(env, NUMBA_CACHE_DIR=cache))
                print(f"whole process, {label}: {time.perf_counter() - started:.2f} s")
    seconds = {engine: [] for engine in engines}
    for _ in range(args.processes):
        for engine in engines:
            started = time.perf_counter()
            subprocess.run(base + ["--engines", engine], check=True, env=env)
            seconds[engine].append(time.perf_counter() - started)
    row = {"variant": args.variants.split(",")[0]}
    for engine in engines:
        row[engine] = statistics.median(seconds[engine])
        print(f"{args.variants.split(',')[0]} {engine:6s} whole process: median {statistics.median(seconds[engine]):7.2f} s "
              f"of {args.processes} ({', '.join(f'{s:.2f}' for s in seconds[engine])})")
    if {"numba", "numpy"} <= set(engines):
        row["ratio"] = row["numpy"] / row["numba"]
    record(args, "_processes", [row], [f"Whole processes: median of {args.processes}, the engines alternating; Python's "
                                       "start, imports, the configuration, the simulation, numba's cache load and the "
                                       "filtering."], {})
    return 0


def main(argv: list[str] | None = None) -> int:
    context = start("benchmarks/bench_study004.py", argv)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", choices=sorted(EXPERIMENTS), default="2")
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=REPEATS, help="filtering-only timings per variant and engine")
    parser.add_argument("--variants", default="ammpf", help="comma-separated: ammpf, sir_mm")
    parser.add_argument("--engines", default="numba,numpy", help="comma-separated: numba, numpy")
    parser.add_argument("--single-runs", type=int, default=0, help="runs also filtered one at a time (0: none)")
    parser.add_argument("--processes", type=int, default=0, help="whole-process timings per engine (0: none)")
    parser.add_argument("--jit", action="store_true", help="with --processes: first a process on an empty numba cache")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--quiet", action="store_true", help=argparse.SUPPRESS)     # a whole-process child
    add_results_argument(parser)
    args = parser.parse_args(argv)
    args.context = context
    if args.runs < 1 or args.repeats < 1 or args.single_runs < 0 or args.processes < 0:
        parser.error("--runs and --repeats must be >= 1, --single-runs and --processes >= 0")
    if args.quiet:                                   # the child of --processes: filter once, print nothing
        cfg, _, reports = reports_for(args.case, args.runs, args.seed)
        make_filter(cfg, args.variants, args.engines).run(reports)
        return 0
    if args.processes:
        return processes(args)
    return filtering(args)


if __name__ == "__main__":
    sys.exit(main())
