"""The stage cache under concurrent jobs in separate processes (issue 7, part 3).

Sweep jobs (joblib, Ray) run in separate processes and share ``<artifacts>/cache``: two jobs that
need the same scenario both look it up, may both compute and store it, and may both find the
same damaged file. What must hold:
- a reader gets exactly the stored table or a miss, never half a file or another file's data;
- a damaged file is moved aside exactly once, however many jobs find it at the same moment, and a
  good file that replaced it in the meantime is never moved aside;
- a job that publishes (copies) a cache file into its run directory gets a complete good file,
  even while another job renames its own copy over the same name.

The first tests replay each dangerous interleaving deterministically (the other job's step is
injected at the exact point, in this process or, where the rename lock must be held against it,
in a second one); the stress test then lets them happen for real: several processes, released
together by a barrier, on the same keys and the same damaged files, round after round; the last
test runs two whole pipeline jobs at the same moment on one cache and compares their tables with
each job run alone, bit for bit.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from pipeline.storage import store
from pipeline.storage.schemas import META_TABLE, META_VERSION, SCHEMA_VERSION
from pipeline.storage.store import META_KEY, StageCache, publish
from tests.helpers.processes import start_code

# full tier (tests/helpers/tiers.py): jobs at once on one cache
pytestmark = pytest.mark.full

ROOT = Path(__file__).resolve().parents[1]
TABLE = "truth"
META = {META_TABLE: TABLE, META_VERSION: SCHEMA_VERSION}


def expected_frame(key: str, rows: int = 20_000) -> pl.DataFrame:
    """The table a stage would compute for ``key``: deterministic, distinct per key."""
    rng = np.random.default_rng(int(key, 16))
    return pl.DataFrame({"run": np.arange(rows) // 100, "x": rng.normal(size=rows), "y": rng.normal(size=rows)})


def key_of(i: int) -> str:
    return f"{0xABC0 + i:016x}"


def damaged_payloads(path: Path, key: str) -> dict[str, bytes]:
    """Three ways a cache file goes bad: cut short, not Parquet at all, a good table under another key."""
    good = path.with_name("good.tmp-build")
    store.atomic_write_parquet(expected_frame(key), good, {**META, META_KEY: key})
    truncated = good.read_bytes()[: good.stat().st_size // 2]
    store.atomic_write_parquet(expected_frame(key), good, {**META, META_KEY: "0" * 16})
    foreign = good.read_bytes()
    good.unlink()
    return {"truncated": truncated, "garbage": b"this is not parquet" * 50, "foreign": foreign}


def place(path: Path, payload: bytes) -> None:
    """Put ``payload`` at ``path`` in one rename, as a damaged file would be found there."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.place")
    tmp.write_bytes(payload)
    os.replace(tmp, path)


# ---- deterministic interleavings ------------------------------------------------------------------

def test_a_file_replaced_between_the_metadata_and_the_data_read_is_read_whole_from_one_file(tmp_path, monkeypatch):
    """The metadata that vouches for a table and the table itself come from the same file."""
    cache = StageCache(tmp_path)
    key, other = key_of(1), key_of(2)
    path = cache.store("scenario", key, expected_frame(key), META)
    real_metadata = pl.read_parquet_metadata

    def metadata_then_another_job_replaces_the_file(source, *args, **kwargs):
        meta = real_metadata(source, *args, **kwargs)
        # another process renames a different table over the path right after our metadata read
        store.atomic_write_parquet(expected_frame(other), path, {**META, META_KEY: key})
        return meta

    monkeypatch.setattr(pl, "read_parquet_metadata", metadata_then_another_job_replaces_the_file)
    df, meta = cache.load("scenario", key, TABLE)
    assert meta[META_KEY] == key
    assert df.equals(expected_frame(key))          # the file whose metadata was checked, not the newcomer


def test_a_damaged_file_that_another_job_already_moved_aside_is_not_moved_again(tmp_path, monkeypatch):
    cache = StageCache(tmp_path)
    key = key_of(3)
    path = cache.path("scenario", key)
    place(path, b"not parquet")
    real_metadata = pl.read_parquet_metadata

    def fails_and_the_other_job_rejects_first(source, *args, **kwargs):
        try:
            return real_metadata(source, *args, **kwargs)
        finally:   # we found it damaged; the other job, which found it too, moves it aside first
            os.replace(path, path.with_name(f"{path.name}.other.rejected"))

    monkeypatch.setattr(pl, "read_parquet_metadata", fails_and_the_other_job_rejects_first)
    assert cache.load("scenario", key, TABLE) is None          # a miss, no FileNotFoundError
    # (hidden files such as the stage's rename lock aside)
    assert [p.name for p in path.parent.iterdir() if not p.name.startswith(".")] == [f"{path.name}.other.rejected"]


def test_a_good_file_stored_while_a_job_was_reading_the_damaged_one_is_kept(tmp_path, monkeypatch):
    cache = StageCache(tmp_path)
    key = key_of(4)
    path = cache.path("scenario", key)
    place(path, b"not parquet")
    real_metadata = pl.read_parquet_metadata

    def fails_while_the_other_job_rejects_recomputes_and_stores(source, *args, **kwargs):
        try:
            return real_metadata(source, *args, **kwargs)
        finally:   # we found it damaged; before we move it aside, the other job has replaced it
            os.replace(path, path.with_name(f"{path.name}.other.rejected"))
            StageCache(tmp_path).store("scenario", key, expected_frame(key), META)

    monkeypatch.setattr(pl, "read_parquet_metadata", fails_while_the_other_job_rejects_recomputes_and_stores)
    assert cache.load("scenario", key, TABLE) is None          # our read failed: recompute, fine
    monkeypatch.undo()
    df, _ = cache.load("scenario", key, TABLE)                 # ... but the other job's good file stayed
    assert df.equals(expected_frame(key))
    assert sorted(p.name for p in path.parent.glob("*.rejected")) == [f"{path.name}.other.rejected"]
    destination = tmp_path / "run" / "truth.parquet"
    publish(path, destination)                                 # so the other job can still publish it
    assert pl.read_parquet(destination).equals(expected_frame(key))


# another job, in its own process, storing one key (it says when it is about to)
STORE_ONE = """
import sys
from pathlib import Path
sys.path.insert(0, sys.argv[4])
import test_concurrent_cache as t
cache = t.StageCache(Path(sys.argv[1]))
Path(sys.argv[3]).touch()
cache.store("scenario", sys.argv[2], t.expected_frame(sys.argv[2]), t.META)
"""


def test_a_store_landing_between_the_check_and_the_move_aside_waits_and_survives(tmp_path, monkeypatch):
    """The narrowest window: we have checked that the name still holds the damaged file, and
    another job's store renames its good file over the name before our move aside. The rename
    lock makes that store wait until the move is done."""
    cache = StageCache(tmp_path)
    key = key_of(6)
    path = cache.path("scenario", key)
    place(path, b"not parquet")
    ready = tmp_path / "other-ready"
    other = start_code(STORE_ONE, str(tmp_path), key, str(ready), str(Path(__file__).parent))
    deadline = time.monotonic() + 60
    while not ready.exists() and time.monotonic() < deadline and other.poll() is None:
        time.sleep(0.01)
    real_stat, stored_meanwhile = os.stat, []

    def stat_then_the_other_store_runs(p, *args, **kwargs):
        result = real_stat(p, *args, **kwargs)
        if Path(p) == path and not stored_meanwhile:
            try:                                     # an unhindered store takes ~10 ms
                other.wait(timeout=1.0)
                stored_meanwhile.append(True)
            except subprocess.TimeoutExpired:        # it waits for our rename lock
                stored_meanwhile.append(False)
        return result

    monkeypatch.setattr(os, "stat", stat_then_the_other_store_runs)
    assert cache.load("scenario", key, TABLE) is None
    monkeypatch.undo()
    assert other.wait(timeout=60) == 0
    assert stored_meanwhile == [False]               # the store could not land inside the window
    df, _ = cache.load("scenario", key, TABLE)       # and its good file is the one under the name
    assert df.equals(expected_frame(key))
    (rejected,) = path.parent.glob("*.rejected")
    assert rejected.read_bytes() == b"not parquet"


def test_a_file_deleted_while_it_is_being_read_gives_its_table_or_a_miss_never_an_error(tmp_path, monkeypatch):
    """E.g. someone clears artifacts/cache during a sweep."""
    cache = StageCache(tmp_path)
    key = key_of(5)
    path = cache.store("scenario", key, expected_frame(key), META)
    real_metadata = pl.read_parquet_metadata

    def deleted_just_before_the_read(source, *args, **kwargs):
        if path.exists():
            path.unlink()
        return real_metadata(source, *args, **kwargs)

    monkeypatch.setattr(pl, "read_parquet_metadata", deleted_just_before_the_read)
    hit = cache.load("scenario", key, TABLE)
    assert hit is None or hit[0].equals(expected_frame(key))
    assert not [p for p in path.parent.iterdir() if not p.name.startswith(".")]   # nothing moved aside or invented


def test_a_hit_is_published_from_the_file_that_was_verified(tmp_path, monkeypatch):
    """Another job renames its copy over the name between our check and our copy: the run still gets
    the file that was read and verified (a copy from the open file, not a second lookup by name)."""
    cache = StageCache(tmp_path / "cache")
    key = key_of(7)
    path = cache.store("scenario", key, expected_frame(key), META)
    real_read = pl.read_parquet
    destination = tmp_path / "run" / "truth.parquet"
    other = path.with_name("other.tmp")
    other.write_bytes(b"another job's file")

    def read_and_rename_over(source, *args, **kwargs):
        try:
            return real_read(source, *args, **kwargs)
        finally:
            os.replace(other, path)                            # the other job's rename, mid-load
    monkeypatch.setattr(pl, "read_parquet", read_and_rename_over)
    df, _ = cache.load("scenario", key, TABLE, publish_to=destination)
    monkeypatch.undo()
    assert df.equals(expected_frame(key)) and real_read(destination).equals(expected_frame(key))
    assert path.read_bytes() == b"another job's file" and destination.stat().st_nlink == 1   # a copy
    with pytest.raises(FileNotFoundError):                     # a source that is gone is an error
        publish(tmp_path / "cache" / "gone.parquet", tmp_path / "run" / "x.parquet")
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == ["truth.parquet"]   # no temp left


# ---- real processes --------------------------------------------------------------------------------

def _hammer(root: str, worker: int, rounds: int, keys: int, barrier, results) -> None:
    """One job: every round, load each key (or compute and store it) and publish it, all workers at once."""
    try:
        logging.getLogger("pipeline.storage.store").setLevel(logging.ERROR)   # the expected "moved aside" warnings
        cache = StageCache(Path(root) / "cache")
        run_dir = Path(root) / f"run{worker}"
        frames = {key_of(k): expected_frame(key_of(k)) for k in range(keys)}
        loaded = stored = 0
        for r in range(rounds):
            barrier.wait()                       # the parent placed damaged files; go together
            for k in (range(keys) if worker % 2 == 0 else reversed(range(keys))):
                key = key_of(k)
                hit = cache.load("scenario", key, TABLE)
                if hit is None:
                    cache.store("scenario", key, frames[key], META)
                    stored += 1
                else:
                    df, meta = hit
                    if meta.get(META_KEY) != key or not df.equals(frames[key]):
                        raise AssertionError(f"round {r}: load of {key} returned another table")
                    loaded += 1
                destination = run_dir / f"{key}-{r}.parquet"
                publish(cache.path("scenario", key), destination)
                if not pl.read_parquet(destination).equals(frames[key]):
                    raise AssertionError(f"round {r}: the published {key} is not the stored table")
            barrier.wait()                       # round done; the parent may damage files again
        results.put((worker, "ok", loaded, stored))
    except BaseException as exc:  # report, and keep the barrier from hanging the others
        barrier.abort()
        results.put((worker, f"{type(exc).__name__}: {exc}", 0, 0))


def test_processes_hitting_the_same_keys_and_the_same_damaged_files_at_once(tmp_path):
    workers, rounds, keys = 4, 20, 3
    context = mp.get_context("spawn")
    barrier = context.Barrier(workers + 1)
    results = context.Queue()
    cache = StageCache(tmp_path / "cache")
    kinds = ["truncated", "garbage", "foreign"]
    payloads = {key_of(k): damaged_payloads(cache.path("scenario", key_of(k)), key_of(k)) for k in range(keys)}
    procs = [context.Process(target=_hammer, args=(str(tmp_path), w, rounds, keys, barrier, results))
             for w in range(workers)]
    for p in procs:
        p.start()
    placed: dict[str, list[bytes]] = {key_of(k): [] for k in range(keys)}
    try:
        for r in range(rounds):
            if r > 0:                                       # round 0: empty cache, everyone computes
                for k in range(keys):
                    key = key_of(k)
                    payload = payloads[key][kinds[(r + k) % len(kinds)]]
                    place(cache.path("scenario", key), payload)
                    placed[key].append(payload)
            barrier.wait(timeout=60)
            barrier.wait(timeout=60)
    except threading.BrokenBarrierError:
        pass                                                # a worker failed: its report says why
    finally:
        for p in procs:
            p.join(timeout=60)
    outcome = sorted(results.get(timeout=5) for _ in procs)
    assert [o[1] for o in outcome] == ["ok"] * workers, outcome
    assert sum(o[2] + o[3] for o in outcome) == workers * rounds * keys
    for k in range(keys):
        key = key_of(k)
        path = cache.path("scenario", key)
        rejected = sorted(path.parent.glob(f"{path.name}.*.rejected"))
        # each damaged file moved aside exactly once, and nothing else: no good file among them
        assert sorted(p.read_bytes() for p in rejected) == sorted(placed[key]), key
        df, _ = StageCache(tmp_path / "cache").load("scenario", key, TABLE)
        assert df.equals(expected_frame(key))
    assert not [p for p in (tmp_path / "cache").rglob("*") if p.name.endswith(".tmp")]   # no temp left


# ---- whole pipeline jobs ---------------------------------------------------------------------------

COMMON = ("mc.runs=3", "mc.seed=7", "record.enabled=false", "scenario.steps=60")
JOBS = {"a": ("variants=[fsimm,vsimm]",), "b": ("variants=[vsimm,ao_vsimm]",)}   # vsimm's estimates shared too
TABLES = ("truth.parquet", "detections.parquet", "estimates/fsimm.parquet", "estimates/vsimm.parquet",
          "estimates/ao_vsimm.parquet", "metrics.parquet")
PROVENANCE = {"run_id", "config_hash", "overrides", "sweep", "job_num"}
# the interpreter imports everything, says it is ready, and starts the job when the test says go
WAIT_THEN_RUN = """
import runpy, sys, time
from pathlib import Path
import pipeline.run.runner, hydra  # the slow imports, before the start signal
ready, go = Path(sys.argv[1]), Path(sys.argv[2])
ready.touch()
while not go.exists():
    time.sleep(0.005)
sys.argv = ["pipeline", *sys.argv[3:]]
runpy.run_module("pipeline", run_name="__main__", alter_sys=True)   # = python -m pipeline ...
"""


def _sequential_tables(artifacts: Path, job: str) -> dict[str, pl.DataFrame]:
    from hydra import compose, initialize_config_dir
    from pipeline.run.runner import RunContext, run_experiment
    overrides = [f"paths.artifacts={artifacts}", *COMMON, *JOBS[job]]
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        cfg = compose("config", overrides=overrides)
    run_experiment(cfg, RunContext(artifacts / "runs" / job, artifacts, overrides))
    return _tables(artifacts / "runs" / job)


def _tables(run_dir: Path) -> dict[str, pl.DataFrame]:
    out = {}
    for name in TABLES:
        if (run_dir / name).exists():
            df = pl.read_parquet(run_dir / name)
            out[name] = df.drop([c for c in df.columns if c in PROVENANCE])
    return out


def test_two_pipeline_jobs_sharing_one_cache_at_once_equal_sequential_runs(tmp_path):
    shared = tmp_path / "concurrent"
    go = tmp_path / "go"
    procs = {job: start_code(
        WAIT_THEN_RUN, str(tmp_path / f"ready-{job}"), str(go), f"paths.artifacts={shared}",
        f"hydra.run.dir={shared}/runs/{job}", *COMMON, *JOBS[job],
        cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for job in JOBS}
    # the reference: each job alone on its own fresh cache (while the two interpreters import)
    expected = {job: _sequential_tables(tmp_path / f"sequential-{job}", job) for job in JOBS}
    deadline = time.monotonic() + 60
    while not all((tmp_path / f"ready-{job}").exists() for job in JOBS) and time.monotonic() < deadline:
        time.sleep(0.01)
    go.touch()                                          # both jobs start now, on one empty cache
    logs = {}
    for job, proc in procs.items():
        out, err = proc.communicate(timeout=120)
        assert proc.returncode == 0, err[-3000:]
        logs[job] = err
    for job in JOBS:
        got = _tables(shared / "runs" / job)
        assert sorted(got) == sorted(expected[job]) and len(got) == 5, (job, sorted(got))
        for name in expected[job]:
            assert got[name].equals(expected[job][name]), (job, name)
    assert not list((shared / "cache").rglob("*.rejected"))
    assert not [p for p in (shared / "cache").rglob("*") if p.name.endswith(".tmp")]
    # one cache file per key, whichever job stored it last: scenario, measure, 3 variants
    assert [len(list((shared / "cache" / s).glob("*.parquet"))) for s in ("scenario", "measure", "track")] == [1, 1, 3]
