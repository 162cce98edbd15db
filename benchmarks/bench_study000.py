"""Study 000 compute benchmark: filters A, A-full, B, C on the spec's scenario (filtering only).

    python benchmarks/bench_study000.py --runs 100

The spec's target: B (decoupled LOS filter, scalar per-axis MIE) costs at most half of A (coupled
inertial filter, 3x3 MIE). Inputs are built from the experiment's own configs. Best of --repeat.
A and A-full are timed with their numpy loops (``engine: numpy``), as B and C have no other: a
comparison of the algorithms needs one technique. A's compiled loop (filters/mie_kernel.py, the
default elsewhere) is the last row, against A's numpy loop.
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

from pipeline.track import measurement_series  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--json", type=Path, default=ROOT / "artifacts" / "benchmarks" / "study000.json")
    args = parser.parse_args()
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
        if hasattr(estimator, "engine"):
            estimator.engine = "numpy"
        seconds = min(estimator.run(series).compute_seconds for _ in range(args.repeat))
        rows.append({"filter": estimator.name, "seconds": seconds})
        if key == "mie_a":
            estimator.engine = "numba"
            compiled = min(estimator.run(series).compute_seconds for _ in range(args.repeat))
    rows.append({"filter": "A, compiled (engine: numba)", "seconds": compiled})
    reference = rows[0]["seconds"]
    print(f"Study 000, {args.runs} runs x {truth.time.size} scans, best of {args.repeat} (filtering only)\n")
    print("| filter | seconds | % of A |\n|---|---:|---:|")
    for row in rows:
        row["pct_of_a"] = 100.0 * row["seconds"] / reference
        print(f"| {row['filter']} | {row['seconds']:.3f} | {row['pct_of_a']:.1f} |")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"runs": args.runs, "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
