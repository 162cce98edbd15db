"""ADS-B study benchmark: the Kalman trackers (CV, CA, Singer) and the CV/CT IMM on a recorded
flight, each with both engines (filtering only).

    python benchmarks/bench_adsb.py --runs 100 --experiment adsb_jet

Inputs are built as the experiment builds them: the Hydra config ``experiment=<experiment>``
composed from ``conf/``, scenario / sensors / study / filters instantiated with
``pipeline.run.config.build``, then ``truth = scenario.generate(R, seed)``,
``detections = sensor.measure(truth, seed)``, ``series = study.track_input(...)`` (the radar's
range/azimuth/elevation, or 2-D positions for the ``*_horizontal`` experiments).

What is timed: ``compute_seconds`` of one ``.run`` over all runs (the filter's own clock: the
measurement conversion, the start, the scans and the output layout; numba's load happens before
it), the median of ``--repeat`` calls, with the compiled loop (``engine: numba``, the default:
filters/tracker/kernel.py) and the numpy scans (``engine: numpy``, the
reference). It also prints the largest difference between the two engines' states, covariances
and NIS, relative to each output's largest entry. No timing assertions.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from hydra import compose, initialize_config_dir  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from benchmarks.results_file import Column, Table, add_results_argument, start, write_result  # noqa: E402
from pipeline.run.config import build  # noqa: E402

VARIANTS = ("kf_cv", "kf_ca", "kf_singer", "imm_cv_ct")


def inputs(experiment: str, runs: int, seed: int):
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        cfg = compose("config", overrides=[f"experiment={experiment}"])
    study = build(cfg.study, "study")
    scenario = build(cfg.scenario, "scenario")
    sensor = build(cfg.sensors, "sensors")
    truth = scenario.generate(runs, seed)
    series = study.track_input(truth, sensor.measure(truth, seed), sensor, seed)
    return cfg, series


def relative_difference(a: np.ndarray, b: np.ndarray) -> float:
    if not np.array_equal(np.isnan(a), np.isnan(b)):
        return float("inf")
    return float(np.nanmax(np.abs(a - b)) / max(float(np.nanmax(np.abs(b))), 1e-300))


def main(argv: list[str] | None = None) -> int:
    context = start("benchmarks/bench_adsb.py", argv)
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--experiment", default="adsb_jet", help="an ADS-B experiment (adsb_*)")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--seed", type=int, default=1)
    add_results_argument(parser)
    args = parser.parse_args(argv)
    if args.runs < 1 or args.repeat < 1:
        parser.error("--runs and --repeat must be >= 1")
    cfg, series = inputs(args.experiment, args.runs, args.seed)
    R, K = series.z.shape[:2]
    kind = "range/azimuth/elevation" if series.z.shape[-1] == 3 else "2-D positions"
    print(f"ADS-B trackers: experiment={args.experiment}, {R} runs x {K} scans of {kind}, median of "
          f"{args.repeat} (filtering only; {platform.machine()}, Python {platform.python_version()})\n")
    print("| filter | compiled | numpy scans | numpy / compiled | max relative difference (state, covariance, NIS) |")
    print("|---|---:|---:|---:|---|")
    rows = []
    for key in VARIANTS:
        if key not in cfg.filters:
            continue
        results, seconds, name = {}, {}, str(cfg.filters[key].get("name", key))
        for engine in ("numba", "numpy"):
            estimator = build(OmegaConf.merge(cfg.filters[key], {"engine": engine}), f"filters.{key}")
            estimator.run(series)                      # numba's load and first call outside the figures
            runs = [estimator.run(series) for _ in range(args.repeat)]
            results[engine] = runs[-1]
            seconds[engine] = statistics.median(r.compute_seconds for r in runs)
        a, b = results["numba"], results["numpy"]
        differences = (relative_difference(a.state, b.state), relative_difference(a.covariance, b.covariance),
                       relative_difference(a.extras["nis"], b.extras["nis"]))
        print(f"| {name} | {seconds['numba']:.3f} s | {seconds['numpy']:.3f} s | "
              f"{seconds['numpy'] / seconds['numba']:.1f}x | {', '.join(f'{d:.1e}' for d in differences)} |")
        rows.append({"filter": name, "compiled": seconds["numba"], "numpy": seconds["numpy"],
                     "ratio": seconds["numpy"] / seconds["numba"], "state": differences[0],
                     "covariance": differences[1], "nis": differences[2]})
    columns = [Column("filter", "filter"), Column("compiled", "compiled", "seconds", ".3f"),
               Column("numpy", "numpy scans", "seconds", ".3f"), Column("ratio", "numpy / compiled", "ratio", ".1f"),
               Column("state", "max rel. difference, state", "number", ".1e"),
               Column("covariance", "covariance", "number", ".1e"), Column("nis", "NIS", "number", ".1e")]
    write_result(args.experiment, f"ADS-B trackers on {args.experiment}: compiled against numpy scans (filtering only)",
                 [Table(columns, rows)],
                 [f"Median of {args.repeat} calls per filter and engine, after one untimed call; the filter's own "
                  "clock (compute_seconds).",
                  "Differences: max |compiled - numpy| relative to each output's largest entry."],
                 context=context, parameters={"experiment": args.experiment, "runs": R, "scans": K,
                                              "measurements": kind, "seed": args.seed},
                 directory=args.results_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
