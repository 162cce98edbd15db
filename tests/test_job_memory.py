"""pipeline.run.memory: what a finished sweep job freed goes back to the operating system before the next
job of a one-process sweep (release_freed_memory), and the peak estimate a refusal relies on is not
below what a job uses (estimate)."""

from __future__ import annotations

import json
import re
import textwrap
from pathlib import Path

import pytest

from tests.helpers.processes import run_code, run_module

# full tier (tests/helpers/tiers.py): peak memory of whole jobs in their own processes
pytestmark = pytest.mark.full

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = textwrap.dedent("""
    import os
    from pipeline.run.memory import release_freed_memory

    def rss():                       # resident bytes now (/proc: the test machines are Linux with glibc)
        return int(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE")

    blocks = [bytes(1000) + bytes([i % 256]) for i in range(350_000)]   # ~350 MB of small malloc blocks
    survivor = bytes(2000)           # pins the heap's top: glibc cannot give back the freed blocks by itself
    del blocks
    before = rss()
    trimmed = release_freed_memory()
    after = rss()
    print(trimmed, before >> 20, after >> 20)
""")


def test_the_heap_a_job_freed_is_returned_to_the_system():
    out = run_code(SCRIPT, check=True, timeout=None).stdout.split()
    trimmed, before_mb, after_mb = out[0] == "True", int(out[1]), int(out[2])
    assert trimmed, "glibc's malloc_trim did not run (this project's machines use glibc)"
    assert before_mb - after_mb > 200, f"RSS {before_mb} MB before, {after_mb} MB after the release"


FREEZE = textwrap.dedent("""
    import gc, weakref
    from pipeline.run.memory import exempt_survivors_from_collection, release_freed_memory

    class Node:
        pass

    def cycle():                     # two objects that only the cyclic collector can free
        a, b = Node(), Node()
        a.other, b.other = b, a
        return a

    held = cycle()
    release_freed_memory()
    walked_before = len(gc.get_objects())     # what a full collection traverses
    first = exempt_survivors_from_collection()
    frozen = gc.get_freeze_count()
    walked_after = len(gc.get_objects())
    second = exempt_survivors_from_collection()
    gone = []
    fresh = cycle()                  # made after the freeze: a later job's garbage
    weakref.finalize(fresh, gone.append, "fresh")
    del fresh
    gc.collect()
    plain = Node()                   # frozen objects are still freed by reference counting
    survivor = [plain]
    gc.collect(); gc.freeze()        # (as if it had lived through the first job)
    weakref.finalize(plain, gone.append, "plain")
    del plain, survivor
    print(first, second, frozen, walked_before, walked_after, " ".join(sorted(gone)))
""")


def test_a_sweeps_long_lived_objects_are_frozen_once_and_later_garbage_still_collected():
    """After a sweep's first job the process freezes what lives on (``gc.freeze``), so later jobs'
    collections do not walk ~200 000 long-lived objects again. Once per process: a second call
    leaves the permanent generation as it is. A cycle made afterwards is still collected, and a
    frozen object is still freed when its last reference goes."""
    out = run_code(FREEZE, check=True, timeout=None).stdout
    first, second, frozen, walked_before, walked_after, *gone = out.split()
    assert (first, second) == ("True", "False")
    assert int(frozen) > 1000, frozen      # the interpreter's and pipeline's objects, the held cycle
    assert int(walked_after) < int(walked_before) // 10, out    # collections no longer walk them
    assert gone == ["fresh", "plain"], out


# ---- the estimate a refusal relies on is never below what the job uses -------------------------------


# the compiling run: the same kernels (numba compiles per argument type, not per size) on a short scenario
COMPILE = {"ao_vsimm_s1": ["scenario.steps=30"], "sonar_case1": ["scenario.duration=300"]}


@pytest.mark.parametrize("experiment", sorted(COMPILE))
def test_the_memory_estimate_is_not_below_a_small_jobs_measured_peak(tmp_path, experiment):
    """A 2-run job is mostly the interpreter and, for study 003's 10 001 steps, the bootstrap's
    (resamples x steps) arrays: both were missing, and the estimate was 0.29 and 0.38 GB against
    peaks of 0.37 and 0.65 GB. The estimate is of a job whose numba kernels are compiled: the first
    job on a fresh clone compiles them, which adds to that job's peak (study 004's particle kernel
    ~0.2 GB), so a short job runs first to compile, and the second run is measured."""
    def run(artifacts: Path, *overrides: str) -> tuple[float, float]:
        proc = run_module("pipeline", f"experiment={experiment}", "mc.runs=2", f"paths.artifacts={artifacts}",
                          *overrides, check=True, timeout=None)
        estimated_gb = float(re.search(r"memory: about ([0-9.]+) GB", proc.stdout + proc.stderr).group(1))
        (status,) = (artifacts / "runs").glob("*/*/status.json")
        return estimated_gb, json.loads(status.read_text())["peak_rss_mb"]

    run(tmp_path / "compiling", *COMPILE[experiment])
    estimated_gb, measured_mb = run(tmp_path / "measured")
    assert estimated_gb * 1024 >= measured_mb, f"estimated {estimated_gb} GB, the job peaked at {measured_mb:.0f} MB"


PARENT = textwrap.dedent("""
    import json, pathlib, subprocess, sys
    import numpy as np

    held = np.ones(700 * 2**20 // 8)                   # a large parent: 700 MB resident
    artifacts = pathlib.Path(sys.argv[1])
    subprocess.run([sys.executable, "-m", "pipeline", "experiment=ao_vsimm_s1", "mc.runs=2", "scenario.steps=30",
                    "record.enabled=false", f"paths.artifacts={artifacts}"], check=True, capture_output=True)
    (status,) = artifacts.glob("runs/*/*/status.json")
    print(json.loads(status.read_text())["peak_rss_mb"])
""")


def test_a_jobs_peak_memory_is_its_own_not_its_parents(tmp_path):
    """status.json's peak_rss_mb came from getrusage's ru_maxrss, which Linux carries over from the
    parent through subprocess's vfork and exec: a job started from a pytest worker reported 831 MB,
    the worker's, for its own 381 MB."""
    out = run_code(PARENT, str(tmp_path), check=True, timeout=None).stdout
    assert float(out.strip()) < 600, f"the job reported {out.strip()} MB, its parent held 700 MB"


def test_the_memory_estimate_does_not_grow_with_the_number_of_variants():
    """A job holds one variant's estimate at a time (pipeline.storage.estimates): the estimate counted every
    variant's (a 7-variant ADS-B flight 1.70 GB estimated against 0.56-0.59 GB measured at 100 runs;
    study 003 5.2 GB against 1.1 GB), so a refusal could stop a job that fits."""
    from omegaconf import open_dict

    from pipeline.run.memory import check
    from pipeline.run.runner import prepare
    from tests.helpers.config import composed

    cfg = composed("adsb_jet", "mc.runs=100", "paths.artifacts=/nonexistent-artifacts")
    with open_dict(cfg):
        cfg.mc.max_memory_gb = 64
    prepared = prepare(cfg)
    assert len(prepared.variants) == 7
    one, seven = (check(cfg, prepared.scenario, prepared.sensor, n).peak for n in (1, 7))
    assert one == seven
    assert seven / 2**30 < 1.0            # 0.93 GB: 0.56-0.59 GB measured (isolated launcher, f15c4b4)
