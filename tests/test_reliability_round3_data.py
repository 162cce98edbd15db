"""Issue 37 (reliability, round 3), items 1-4, 17, 19 and 20: data a failure must not lose, and
refusals that must be one paragraph, each with the case that went wrong."""

from __future__ import annotations

import json
import os
from pathlib import Path

import polars as pl
import pytest

from tests.helpers.processes import run_pipeline, start_code
from tests.helpers.runs import job


# ---- item 1: a refused run removes only what it created ---------------------------------------------

def test_a_refused_run_into_an_existing_folder_keeps_every_file_of_it(tmp_path):
    """Item 1: ``hydra.run.dir=<an existing folder> mc.runs=0`` removed the folder (rmtree), the
    user's files with it (a folder holding only ``*.log`` files passed for Hydra's own)."""
    mine = tmp_path / "mine"
    (mine / "sub").mkdir(parents=True)
    (mine / "important.log").write_text("the user's log\n")
    (mine / "sub" / "data.csv").write_text("1,2\n")
    logs = tmp_path / "logs_only"
    logs.mkdir()
    (logs / "server.log").write_text("kept\n")
    empty = tmp_path / "empty_but_mine"
    empty.mkdir()
    for folder in (mine, logs, empty):
        proc = run_pipeline(f"hydra.run.dir={folder}", "mc.runs=0", artifacts=tmp_path)
        assert proc.returncode == 2 and "error: mc.runs: 0 is not allowed" in proc.stderr
        assert folder.is_dir()
    assert (mine / "important.log").read_text() == "the user's log\n"
    assert (mine / "sub" / "data.csv").read_text() == "1,2\n"
    # what the refused job made (Hydra's .hydra/ and its log) is gone again; the user's files stay
    assert sorted(p.relative_to(mine).as_posix() for p in mine.rglob("*")) == ["important.log", "sub", "sub/data.csv"]
    assert [p.name for p in logs.iterdir()] == ["server.log"] and (logs / "server.log").read_text() == "kept\n"
    assert list(empty.iterdir()) == []


def test_a_refused_run_into_a_finished_runs_folder_leaves_its_results(tmp_path):
    """Item 1: a refused rerun into a finished run's folder wrote its failure over that run's
    status.json and summary.parquet (the folder held a status.json, taken as 'this job started')."""
    run = tmp_path / "done"
    assert run_pipeline(f"hydra.run.dir={run}", "mc.runs=2", "scenario.steps=20",
                        "record.enabled=false", artifacts=tmp_path).returncode == 0
    before = {p.relative_to(run).as_posix(): p.read_bytes() for p in run.rglob("*") if p.is_file()
              and ".hydra" not in p.parts and not p.name.endswith(".log")}
    proc = run_pipeline(f"hydra.run.dir={run}", "mc.runs=0", artifacts=tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    after = {p.relative_to(run).as_posix(): p.read_bytes() for p in run.rglob("*") if p.is_file()
             and ".hydra" not in p.parts and not p.name.endswith(".log")}
    assert after == before
    assert json.loads((run / "status.json").read_text())["status"] == "ok"


# ---- item 2: a failed publish is the run folder's failure, never the cache file's -----------------

def _as_the_cli_runs_it(cfg, ctx) -> int | None:
    """``python -m pipeline``'s single-run handling of a job (pipeline.__main__._run): its exit code."""
    from pipeline.__main__ import _run
    try:
        _run(cfg, None, False, ctx)
    except SystemExit as exc:
        return exc.code
    return 0


def _full_disk_under(monkeypatch, folder: Path) -> None:
    """Every new file under ``folder`` fails with ENOSPC, as on a full disk (the files there keep their
    bytes): a temp file is refused, and so is a copy's first byte."""
    import errno
    import tempfile as tempfile_module

    from pipeline.storage import store

    real_mkstemp, real_copy = tempfile_module.mkstemp, store._clone_or_copy

    def mkstemp(*args, dir=None, **kwargs):
        if dir is not None and Path(dir).resolve().is_relative_to(folder.resolve()):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_mkstemp(*args, dir=dir, **kwargs)

    def clone_or_copy(source, target):
        if Path(target.name).resolve().is_relative_to(folder.resolve()):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_copy(source, target)

    monkeypatch.setattr(store.tempfile, "mkstemp", mkstemp)
    monkeypatch.setattr(store, "_clone_or_copy", clone_or_copy)


def test_a_cache_hit_that_cannot_be_published_keeps_the_cache_file_and_ends_the_job_failed(tmp_path, monkeypatch,
                                                                                              capsys):
    """Item 2: with the run folder on a full disk, a cache hit that could not be copied was reported
    'cannot be read' and moved aside as ``*.rejected``; status.json stayed ``running``."""
    from pipeline.run.runner import run_experiment
    run_experiment(*job(tmp_path, "first", "mc.runs=2", "scenario.steps=20"))
    cache = {p: p.read_bytes() for p in (tmp_path / "cache").rglob("*.parquet")}
    cfg, ctx = job(tmp_path, "second", "mc.runs=2", "scenario.steps=20")
    from pipeline.storage.store import StageCache
    real_load = StageCache.load

    def fill_the_disk_then_load(self, *args, **kwargs):
        _full_disk_under(monkeypatch, ctx.run_dir)   # its status.json and config.yaml are written: now it is full
        return real_load(self, *args, **kwargs)

    monkeypatch.setattr(StageCache, "load", fill_the_disk_then_load)
    assert _as_the_cli_runs_it(cfg, ctx) == 2
    err = capsys.readouterr().err
    assert f"error: cannot write {ctx.run_dir / 'truth.parquet'}: No space left on device" in err
    assert not list((tmp_path / "cache").rglob("*.rejected"))
    assert {p: p.read_bytes() for p in (tmp_path / "cache").rglob("*.parquet")} == cache
    status = json.loads((ctx.run_dir / "status.json").read_text())
    assert status["status"] == "failed" and "No space left on device" in status["error"]
    assert status["finished_at"] is not None
    assert not [p for p in ctx.run_dir.rglob("*") if p.name.endswith(".tmp")]


# ---- item 3: record.runs checked up front; a failed recording keeps the tables ----------------------

@pytest.mark.parametrize("record_runs, message", [
    ("[0,1,1]", r"record.runs: \[0, 1, 1\] lists run\(s\) \[1\] more than once; each recorded run is listed once, "
                r"e.g. record.runs=\[0, 1\]"),
    ("[0,2]", r"record.runs: \[0, 2\] holds run index\(es\) \[2\] outside the 2 Monte Carlo runs"),
    ("[-1]", r"record.runs: \[-1\] holds run index\(es\) \[-1\] outside"),
])
def test_record_runs_are_checked_before_any_stage(tmp_path, record_runs, message):
    """Item 3: record.runs=[0,1,1] failed with a traceback after every stage had run."""
    from pipeline.errors import ConfigError
    from pipeline.run.runner import run_experiment
    with pytest.raises(ConfigError, match=message):
        run_experiment(*job(tmp_path, "bad", "mc.runs=2", "record.enabled=true", f"record.runs={record_runs}"))
    assert not (tmp_path / "cache").exists() and not (tmp_path / "runs").exists()


def test_a_failure_in_the_record_stage_keeps_the_computed_tables(tmp_path, monkeypatch, capsys):
    """Item 3: a failure in the record stage replaced summary.parquet by the one-row failure summary,
    though the tables had been written and the message said so."""
    from pipeline.errors import StorageError
    from pipeline.storage.store import read_table
    from pipeline.studies.single_target import SingleTargetStudy

    def record(self, path, inputs):
        raise StorageError(f"cannot write {path}: No space left on device. Nothing was left under that name; "
                           f"the tables were written before the recording; record.enabled=false skips it.")

    monkeypatch.setattr(SingleTargetStudy, "record", record)
    cfg, ctx = job(tmp_path, "rec", "mc.runs=2", "scenario.steps=20", "record.enabled=true")
    assert _as_the_cli_runs_it(cfg, ctx) == 2
    assert "the tables were written before the recording" in capsys.readouterr().err
    summary, _ = read_table(ctx.run_dir / "summary.parquet")            # whole, its checksum verified
    assert summary.height > 1 and set(summary["status"]) == {"ok"} and summary["value"].is_not_null().any()
    for name in ("metrics", "comparisons", "per_run", "resamples"):
        read_table(ctx.run_dir / f"{name}.parquet")
    assert "FSIMM" in (ctx.run_dir / "report.txt").read_text()
    status = json.loads((ctx.run_dir / "status.json").read_text())
    assert status["status"] == "failed" and "recording.rrd" in status["error"]


# ---- item 4: temp files of killed jobs are cleaned from the cache, a live writer's never -------------

_WRITE_AND_STOP = """
import os, signal, sys, time
import polars as pl
from pipeline.storage.store import StageCache
stream = StageCache(sys.argv[1]).stream("track", "abc")
stream.write(pl.DataFrame({"x": list(range(1000))}))       # a chunk on disk, never renamed
print(stream.tmp.name, flush=True)
if sys.argv[2] == "kill":
    os.kill(os.getpid(), signal.SIGKILL)                     # as the OOM killer would
time.sleep(60)                                               # a live writer, between two chunks
"""


def _writer(cache: Path, how: str):
    import subprocess
    proc = start_code(_WRITE_AND_STOP, str(cache), how, stdout=subprocess.PIPE, text=True)
    name = proc.stdout.readline().strip()
    return proc, cache / "track" / name


def test_temp_files_of_killed_jobs_are_removed_from_the_cache_and_a_live_writers_kept(tmp_path, caplog):
    """Item 4: SIGKILL left orphaned ``.*.tmp`` files in the cache (190 MB after four kills), never
    cleaned. The next job that uses the stage removes those whose writer is gone; a writer still
    running keeps its file, and one this machine cannot check is left for ORPHAN_GRACE_S."""
    import logging
    import signal
    import time

    from pipeline.storage.store import ORPHAN_GRACE_S, StageCache
    cache = tmp_path / "cache"
    killed, killed_tmp = _writer(cache, "kill")
    assert killed.wait(timeout=60) == -signal.SIGKILL and killed_tmp.is_file()
    alive, alive_tmp = _writer(cache, "live")
    try:
        own = StageCache(cache).stream("track", "own")             # this process's, unfinished
        own.write(pl.DataFrame({"x": [1]}))
        old = time.time() - ORPHAN_GRACE_S - 60
        unknown_old, unknown_new = cache / "track" / ".k.parquet.x1y2.tmp", cache / "track" / ".n.parquet.z3.tmp"
        elsewhere_old = cache / "track" / ".e.parquet.wffffffeeeeee-12-34.abcd.tmp"     # another host's writer
        for path in (unknown_old, unknown_new, elsewhere_old):
            path.write_bytes(b"PAR1")
        for path in (unknown_old, elsewhere_old):
            os.utime(path, (old, old))
        caplog.set_level(logging.INFO)
        assert StageCache(cache).load("track", "abc", "estimates") is None
        assert not killed_tmp.exists() and not unknown_old.exists() and not elsewhere_old.exists()
        assert alive_tmp.is_file() and own.tmp.is_file() and unknown_new.is_file()
        assert "cache/track: removed 3 temp file(s)" in caplog.text
    finally:
        alive.kill()
        alive.wait(timeout=60)
    StageCache(cache).load("track", "abc", "estimates")           # its writer gone now: removed too
    assert not alive_tmp.exists() and own.tmp.is_file()
    own.abort()


# ---- item 17: one paragraph, exit 2, for what a user or the machine did -----------------------------

def test_a_full_disk_during_the_track_stages_cache_write_is_one_paragraph(tmp_path, monkeypatch, capsys):
    """Item 17: polars reports a full disk as ``ComputeError: ... (os error 28)``, which went through as
    a traceback with exit 1 (an OSError was the only write failure handled)."""
    from pipeline.storage.store import META_KEY
    from pipeline.storage.schemas import META_TABLE
    real = pl.DataFrame.write_parquet

    def write_parquet(self, file, *args, metadata=None, **kwargs):
        if metadata and META_KEY in metadata and metadata.get(META_TABLE) not in ("truth", "detections"):
            real(self, file, *args, metadata=metadata, **kwargs)     # some bytes out, then the disk is full
            raise pl.exceptions.ComputeError("parquet: File out of specification: underlying IO error: No space "
                                             "left on device (os error 28)")
        return real(self, file, *args, metadata=metadata, **kwargs)

    monkeypatch.setattr(pl.DataFrame, "write_parquet", write_parquet)
    cfg, ctx = job(tmp_path, "full", "mc.runs=2", "scenario.steps=20")
    assert _as_the_cli_runs_it(cfg, ctx) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: cannot write {tmp_path / 'cache' / 'track'}/") and "\n" not in err
    assert "No space left on device. The disk is full" in err
    assert not list((tmp_path / "cache" / "track").glob("*.parquet"))
    assert not [p for p in tmp_path.rglob("*") if p.name.endswith(".tmp")]
    assert json.loads((ctx.run_dir / "status.json").read_text())["status"] == "failed"


def test_a_damaged_file_in_a_read_only_cache_is_one_paragraph(tmp_path, monkeypatch, capsys):
    """Item 17: a damaged cache file on a read-only cache raised the lock's OSError with a traceback."""
    import errno

    from pipeline.run.runner import run_experiment
    from pipeline.storage import store
    run_experiment(*job(tmp_path, "first", "mc.runs=2", "scenario.steps=20"))
    (cached,) = (tmp_path / "cache" / "scenario").glob("*.parquet")
    data = bytearray(cached.read_bytes())
    data[len(data) // 2] ^= 0xFF                                      # a flipped byte in a data page
    cached.write_bytes(bytes(data))

    def read_only(directory):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(directory / ".lock"))

    monkeypatch.setattr(store, "_renames_locked", read_only)
    cfg, ctx = job(tmp_path, "second", "mc.runs=2", "scenario.steps=20")
    assert _as_the_cli_runs_it(cfg, ctx) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: cache file {cached} cannot be used: ") and "\n" not in err
    assert "It cannot be moved aside and the stage recomputed into the cache: cannot write in " in err
    assert "Read-only file system. That file system is read-only" in err
    assert cached.read_bytes() == bytes(data)                        # left as it was


def _two_runs(tmp_path: Path) -> list[Path]:
    from pipeline.run.runner import run_experiment
    folders = []
    for name in ("a", "b"):
        cfg, ctx = job(tmp_path, name, "mc.runs=2", "scenario.steps=20")
        run_experiment(cfg, ctx)
        folders.append(ctx.run_dir)
    return folders


def test_a_run_folder_deleted_while_a_query_reads_it_is_left_out_with_a_warning(tmp_path, monkeypatch):
    """Item 17: a run folder removed between the query's listing and its reading raised polars'
    FileNotFoundError with a traceback."""
    import shutil

    from pipeline.results import query as q
    kept, removed = _two_runs(tmp_path)
    real = q._execute
    warnings = []

    def remove_then_execute(sql, tables):
        shutil.rmtree(removed, ignore_errors=True)      # after the catalog listed and checked its files
        return real(sql, tables)

    monkeypatch.setattr(q, "_execute", remove_then_execute)
    out = q.query("SELECT DISTINCT run_id FROM summary", root=tmp_path, warn=warnings.append)
    assert out["run_id"].to_list() == ["runs/a"]
    assert any(f"skipping {removed / 'summary.parquet'}: it was removed while the query read it" in w
               for w in warnings)


def test_a_table_function_on_a_missing_file_is_a_query_error(tmp_path):
    """Item 17: ``"read_ipc"('<missing>')`` (a quoted name, past the text check) ended in polars'
    FileNotFoundError with a traceback; whatever refuses it, it is one QueryError."""
    from pipeline.results.query import QueryError, query
    _two_runs(tmp_path)
    with pytest.raises(QueryError):
        query(f"""SELECT * FROM "read_ipc"('{tmp_path / "missing.arrow"}')""", root=tmp_path)


@pytest.mark.parametrize("text, holds", [("- a\n- b\n", "holds a list: ['a', 'b']"),
                                         ("just a string\n", "holds a mapping without '# @package _global_'"),
                                         ("mc:\n  runs: 2\n", "holds a mapping without '# @package _global_'")])
def test_an_experiment_file_that_is_not_a_global_mapping_is_one_paragraph(tmp_path, text, holds):
    """Item 17: an experiment YAML holding a list or a string failed with a traceback (the run folder's
    name interpolates experiment_name, which it never set)."""
    (tmp_path / "extra" / "experiment").mkdir(parents=True)
    (tmp_path / "extra" / "experiment" / "odd.yaml").write_text(text)
    proc = run_pipeline(f"--config-dir={tmp_path / 'extra'}", "experiment=odd", "mc.runs=2", artifacts=tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    (line,) = proc.stderr.strip().splitlines()
    assert line.startswith(f"error: experiment=odd: conf/experiment/odd.yaml (or the --config-dir file of that "
                           f"name) {holds}") and "'# @package _global_' and which sets experiment_name" in line
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("seed", [2**63, 2**70])
def test_a_seed_beyond_64_bits_is_refused_up_front(tmp_path, seed):
    """Item 17: mc.seed=2**70 ran every stage, then failed writing the summary (polars: cannot convert i128)."""
    from pipeline.errors import ConfigError
    from pipeline.run.config import validate
    from pipeline.run.runner import run_experiment
    with pytest.raises(ConfigError, match=rf"mc.seed: {seed} is not allowed; the seed must be an integer from 0 to "
                                          rf"{2**63 - 1} \(2\*\*63 - 1"):
        run_experiment(*job(tmp_path, "bad", "mc.runs=2", f"mc.seed={seed}"))
    assert not (tmp_path / "cache").exists()
    cfg, _ = job(tmp_path, "largest", "mc.runs=2", f"mc.seed={2**63 - 1}")
    validate(cfg)                                                      # the largest is allowed
