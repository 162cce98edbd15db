"""``python -m pipeline.run.warmup``: compile every numba kernel once, right after installing, by a short
job of each study (its ``smoke`` overrides, 2 Monte Carlo runs, no cache, no recording, in a temporary
folder), so that the first real job does not spend its first minute compiling.

numba keeps what it compiles beside the kernels' source (``__pycache__``), so this is needed once per
install (and again after an edit of a kernel file or a numba upgrade). Each kernel family says when it
compiles and how long it took (filters.compiling); ``--experiments`` limits the jobs to some.
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
from pathlib import Path
from typing import Sequence

CONF = Path(__file__).resolve().parents[2] / "conf"


def smoke_experiments() -> list[tuple[str, list[str]]]:
    """(experiment, its smoke overrides) for every experiment that sets ``smoke`` (one per study)."""
    from hydra import compose, initialize_config_dir
    found = []
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        for path in sorted((CONF / "experiment").glob("*.yaml")):
            smoke = compose("config", overrides=[f"experiment={path.stem}"]).get("smoke")
            if smoke is not None:
                found.append((path.stem, [str(o) for o in smoke]))
    return found


def warm_up(experiments: Sequence[str] | None = None) -> list[tuple[str, float, str | None]]:
    """Run each study's smoke job; (experiment, seconds, the error or None) each."""
    from hydra import compose, initialize_config_dir

    from pipeline.run.runner import RunContext, run_experiment
    chosen = [(name, smoke) for name, smoke in smoke_experiments() if not experiments or name in experiments]
    done = []
    with tempfile.TemporaryDirectory(prefix="mtt-warmup-") as folder, \
            initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        for name, smoke in chosen:
            overrides = [f"experiment={name}", *smoke, "mc.runs=2", "record.enabled=false", "cache.enabled=false",
                         "timing.budget_s=0", f"paths.artifacts={folder}"]
            started = time.perf_counter()
            error = None
            try:
                cfg = compose("config", overrides=overrides)
                run_experiment(cfg, RunContext(Path(folder) / "runs" / name, Path(folder), overrides))
            except Exception as exc:        # a study whose extra is not installed: the others still warm up
                error = f"{type(exc).__name__}: {exc}"
            done.append((name, time.perf_counter() - started, error))
            logging.getLogger("warmup").info("[warmup] %s: %.1f s%s", name, done[-1][1],
                                               f" (failed: {error})" if error else "")
    return done


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline.run.warmup", description=__doc__.split("\n\n")[0])
    parser.add_argument("--experiments", nargs="*", help="only these experiments' jobs (default: one per study)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s] %(message)s", datefmt="%H:%M:%S", stream=sys.stderr)
    # the jobs' own tables and stage lines are not what this command is for
    logging.getLogger("pipeline").setLevel(logging.WARNING)
    done = warm_up(args.experiments)
    for name, seconds, error in done:
        print(f"{name}: {seconds:.1f} s" + (f", failed: {error}" if error else ""))
    if not done:
        print(f"no experiment with a smoke run among {args.experiments}", file=sys.stderr)
        return 2
    return 1 if any(error for _, _, error in done) else 0


if __name__ == "__main__":
    sys.exit(main())
