"""How much memory a job will need at its peak, estimated before any stage; refused if more than the
machine has (``mc.max_memory_gb``, default: what is available when the job starts).

The estimate is built from one run of the scenario and the sensor (a few ms), the size of the
filters' output and the bootstrap's size. A job holds the truth and the measurements of all runs
(each beside its table while written), and one variant's estimate at a time (pipeline.storage.estimates):
at the peak, a variant's track stage holds the filter's output, its table and the estimate decoded
from it; what the evaluation keeps of each variant (per-step values, bootstrap resamples, per-run
values) does not grow with the steps times the runs. The intervals resample the runs at every
step, in arrays of (resamples x steps) that do not grow with the runs. So::

    500 MB + 3 x resamples x steps x 8 B + runs x (2 (truth + measurements) + 3 max (estimate))

with an estimate of K steps x T objects x (n + n^2) float64 times 2 (the filters' extras: mode
probabilities, NIS, ...). The 500 MB is the interpreter with what a job loads (numpy, polars,
Hydra, scipy.stats, numba and a compiled kernel, rerun for the recording). Against the measured
peaks of all 24 experiments (whole process, its recording included, status.json's ``peak_rss_mb``:
the job's own VmHWM; isolated launcher, f15c4b4's holding): 1.08-1.99x at 2 runs (the
particle-filter jobs closest, 1.08-1.21: the baseline is most of their estimate), 1.33-3.02x at the
paper's size (study 003 100 runs 3.28 GB estimated / 1.08-1.11 GB measured: its compact tables
hold float32 covariance triangles, a quarter of the float64 squares counted here; study 002 1.91 /
0.79-0.81: 32 targets, small bias estimates). Never below, which is what a refusal needs. The
formula before counted every variant's estimates (``+ sum over variants (estimate) + 2 max``), as
jobs held them until f15c4b4: against today's peaks it gave 1.10-4.80x (study 003 5.2 GB). Before
the bootstrap term and this baseline, a 2-run study 003 job was estimated at 0.38 GB and peaked at
0.65 GB, and the paper-size study 001 and horizontal ADS-B jobs were estimated at 0.86-0.93x their
own peaks. The estimate is of a job whose numba kernels are
compiled (``__pycache__``): the first job after an install compiles the ones it uses, which adds
to that job's peak (2 runs in a fresh tree: study 004 663 MB compiling the particle kernel, 481 MB
after, against 543 MB estimated; study 001 404 MB, then 369 MB).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import ConfigError
from pipeline.evaluation.uncertainty import RESAMPLES

BASELINE_BYTES = 500 * 2**20
EXTRAS_FACTOR = 2.0
BOOTSTRAP_ARRAYS = 3
TRACK_STAGE_COPIES = 3           # the filter's output, its table, the estimate decoded from the table


def _nbytes(obj: Any) -> int:
    total = 0
    for value in vars(obj).values():
        if isinstance(value, np.ndarray):
            total += value.nbytes
        elif isinstance(value, dict):
            total += sum(v.nbytes for v in value.values() if isinstance(v, np.ndarray))
    return total


def available_bytes() -> int | None:
    """MemAvailable, or less where a cgroup (a container, a job scheduler) limits this process."""
    available = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                available = int(line.split()[1]) * 1024
    except OSError:
        try:
            available = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):
            return None
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max":
            used = int(Path("/sys/fs/cgroup/memory.current").read_text())
            available = min(available or 2**62, int(limit) - used)
    except (OSError, ValueError):
        pass
    return available


@dataclass(frozen=True)
class MemoryEstimate:
    runs: int
    steps: int
    per_run_inputs: int          # truth + measurements, bytes per run
    per_run_estimates: int       # one variant's track stage (filter output, table, decoded), bytes per run
    per_run_peak: int            # the estimate's bytes per run at the peak
    fixed: int = 0               # what does not grow with the runs: the bootstrap's (resamples x steps) arrays

    @property
    def peak(self) -> int:
        return BASELINE_BYTES + self.fixed + self.runs * self.per_run_peak

    def max_runs(self, budget: int) -> int:
        return max(0, (budget - BASELINE_BYTES - self.fixed) // max(self.per_run_peak, 1))


def estimate(scenario: Any, sensor: Any, runs: int, seed: int, resamples: int = RESAMPLES) -> MemoryEstimate:
    """The peak estimate from one run of the scenario and the sensor (see the module docstring)."""
    truth = scenario.generate(1, seed)
    inputs = _nbytes(truth) + _nbytes(sensor.measure(truth, seed))
    _, K, T, n = truth.state.shape
    per_variant = int(K * T * (n + n * n) * 8 * EXTRAS_FACTOR)
    track_stage = TRACK_STAGE_COPIES * per_variant              # whatever the number of variants
    return MemoryEstimate(runs, K, inputs, track_stage, 2 * inputs + track_stage,
                          BOOTSTRAP_ARRAYS * resamples * K * 8)


def check(cfg: Any, scenario: Any, sensor: Any, variants: int) -> MemoryEstimate:
    """Refuse (ConfigError) a job whose estimated peak exceeds ``mc.max_memory_gb`` or, when that is
    null, the memory available now; return the estimate (the runner logs it)."""
    runs, seed = int(cfg.mc.runs), int(cfg.mc.seed)
    resamples = int((cfg.get("uncertainty") or {}).get("bootstrap_resamples", RESAMPLES))
    guess = estimate(scenario, sensor, runs, seed, resamples)
    limit_gb = cfg.mc.get("max_memory_gb")
    if limit_gb is not None and (isinstance(limit_gb, bool) or not isinstance(limit_gb, (int, float)) or limit_gb <= 0):
        raise ConfigError(f"mc.max_memory_gb: {limit_gb!r} is not allowed; it must be a number of GB > 0, or null "
                          f"(the memory available when the job starts).")
    budget = int(limit_gb * 2**30) if limit_gb is not None else available_bytes()
    if budget is not None and guess.peak > budget:
        where = f"mc.max_memory_gb={limit_gb}" if limit_gb is not None else "available on this machine now"
        raise ConfigError(
            f"mc.runs: {runs} runs need about {guess.peak / 2**30:.1f} GB at the job's peak (estimated from one run: "
            f"{guess.steps} steps, truth and measurements {guess.per_run_inputs * runs / 2**20:,.0f} MB, a "
            f"variant's track stage {guess.per_run_estimates * runs / 2**20:,.0f} MB, one of the {variants} at a "
            f"time), more than the "
            f"{budget / 2**30:.1f} GB {where}. Lower mc.runs to at most {guess.max_runs(budget)} (several jobs "
            f"with different mc.seed give independent runs), or, if the estimate is too cautious for your "
            f"filters, set mc.max_memory_gb to what the job may use. Nothing was computed.")
    return guess


def release_freed_memory() -> bool:
    """Hand the memory a finished job freed back to the operating system, so the next job of a
    one-process sweep (Hydra's basic launcher) starts from less: collect cycles, then ask glibc's
    allocator to return its free heap pages (``malloc_trim(0)``). Freed small blocks otherwise stay
    in the process's heap, counted in its RSS. Measured on four paper-size jobs run one after the other
    (ADS-B, study 002, 004 and 003 last): the process held 699 MB when the sonar job started, 536 MB with
    this, and the sweep's peak went from 1904 to 1821 MB. Returns whether glibc's trim ran (False on
    another C library, where only the collection happens)."""
    import ctypes
    import gc

    gc.collect()
    try:
        trim = ctypes.CDLL(None).malloc_trim    # the process's own symbols: glibc's, if it is glibc
    except (OSError, AttributeError):
        return False
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    trim(0)
    return True


def exempt_survivors_from_collection() -> bool:
    """Move every object alive now into the cyclic collector's permanent generation (``gc.freeze``),
    once per process; call it after ``release_freed_memory`` at the end of a sweep's job.

    A full collection traverses every tracked object. After its first job a sweep's process holds
    ~200 000 of them that live as long as it does (modules, numba's type system, scipy's and
    Hydra's tables), so each later job's ``gc.collect`` (0.09 s measured in one process, more in a
    pooled worker) and every automatic full collection inside a job walked them again. Frozen, they
    are skipped; reference counting still frees them. What the first job left alive is frozen with
    them, and a reference cycle among those that later becomes garbage is not collected: a bounded,
    one-time cost (+2.5 MB at the peak of a 26-job pooled sweep). Returns whether this call froze."""
    import gc

    if gc.get_freeze_count():
        return False
    gc.freeze()
    return True


def own_peak_rss_mb() -> float:
    """This process's own peak resident memory in MB: ``VmHWM`` of /proc/self/status (Linux), which
    counts this program only, from its start. ``getrusage``'s ``ru_maxrss`` is not that: Linux keeps
    the larger of the parent's high-water mark across a vfork and exec, which is how Python's
    subprocess starts programs, so a job started from a large process (a test runner, a notebook,
    a launcher) reported its parent's peak (a 2-run study 001 job said 831 MB from a pytest worker;
    its own peak was 381 MB). ``ru_maxrss`` where /proc is missing."""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    import resource
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
