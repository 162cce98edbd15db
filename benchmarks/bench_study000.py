"""Study 000 compute benchmark: filters A, A-full, B, C on the spec's scenario (filtering only).

    python benchmarks/bench_study000.py --runs 100

The spec's target: B (decoupled LOS filter, scalar per-axis MIE) costs at most half of A (coupled
inertial filter, 3x3 MIE). Inputs are built from the experiment's own configs. Best of --repeat.
Each filter is timed with both engines, the compiled loop (``engine: numba``, filters/input_estimation/kernel.py,
the default) and the numpy scans (``engine: numpy``); "% of A" compares within one engine: a
comparison of the algorithms needs one implementation technique.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from hydra.utils import instantiate  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from benchmarks.results_file import Column, Table, add_results_argument, start, write_result  # noqa: E402
from pipeline.studies.single_target import measurement_series  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    context = start("benchmarks/bench_study000.py", argv)
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--json", type=Path, default=ROOT / "artifacts" / "benchmarks" / "study000.json")
    add_results_argument(parser)
    args = parser.parse_args(argv)
    conf = ROOT / "conf"
    truth = instantiate(OmegaConf.load(conf / "scenario" / "mie_los.yaml"), _convert_="all").generate(args.runs, args.seed)
    detections = instantiate(OmegaConf.load(conf / "sensors" / "mie_los.yaml"), _convert_="all").measure(truth, args.seed)
    series = measurement_series(detections)
    rows = []
    for key in ("mie_a", "mie_a_full", "mie_b", "mie_c"):
        node = OmegaConf.load(conf / "filter" / f"{key}.yaml")
        if "defaults" in node:
            base = OmegaConf.load(conf / "filter" / f"{node.defaults[0]}.yaml")
            node = OmegaConf.merge(base, {k: v for k, v in node.items() if k != "defaults"})
        estimator = instantiate(node, _convert_="all")
        seconds = {}
        for engine in ("numba", "numpy"):
            estimator.engine = engine
            seconds[engine] = min(estimator.run(series).compute_seconds for _ in range(args.repeat))
        rows.append({"filter": estimator.name, "seconds": seconds["numba"], "numpy_seconds": seconds["numpy"]})
    reference, numpy_reference = rows[0]["seconds"], rows[0]["numpy_seconds"]
    print(f"Study 000, {args.runs} runs x {truth.time.size} scans, best of {args.repeat} (filtering only)\n")
    print("| filter | compiled | % of A | numpy | % of A |\n|---|---:|---:|---:|---:|")
    for row in rows:
        row["pct_of_a"] = 100.0 * row["seconds"] / reference
        row["numpy_pct_of_a"] = 100.0 * row["numpy_seconds"] / numpy_reference
        print(f"| {row['filter']} | {row['seconds']:.4f} | {row['pct_of_a']:.1f} | {row['numpy_seconds']:.3f} | "
              f"{row['numpy_pct_of_a']:.1f} |")
        row["numpy_over_compiled"] = row["numpy_seconds"] / row["seconds"]
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"runs": args.runs, "rows": rows}, indent=2))
    columns = [Column("filter", "filter"), Column("seconds", "compiled", "seconds", ".4f"),
               Column("pct_of_a", "compiled, of A", "percent", ".1f"),
               Column("numpy_seconds", "numpy scans", "seconds", ".3f"),
               Column("numpy_pct_of_a", "numpy, of A", "percent", ".1f"),
               Column("numpy_over_compiled", "numpy / compiled", "ratio", ".1f")]
    write_result("study000", "Study 000: the input-estimation filters A, A-full, B, C (filtering only)",
                 [Table(columns, rows)],
                 [f"Best of {args.repeat} calls per filter and engine; the filter's own clock (compute_seconds).",
                  "The spec's target: B (decoupled LOS filter) costs at most half of A; '% of A' compares "
                  "within one engine."],
                 context=context, parameters={"runs": args.runs, "scans": truth.time.size, "seed": args.seed},
                 directory=args.results_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
