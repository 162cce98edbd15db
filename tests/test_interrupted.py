"""Interrupted runs: a pipeline process SIGKILLed while it writes a stage's Parquet (half-written,
or written but not yet renamed) or the .rrd leaves no corrupt or partial file under a final name;
the re-run completes, and its tables equal an uninterrupted run's bit for bit."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import polars as pl
import pytest

from tests.helpers.assertions import assert_same_tables
from tests.helpers.processes import run_pipeline, start_script

# full tier (tests/helpers/tiers.py): jobs killed mid-write
pytestmark = pytest.mark.full

ROOT = Path(__file__).resolve().parents[1]
ARGS = ["experiment=mie_los", "mc.runs=4", "variants=[a,b]"]


def run(artifacts: Path, *extra: str) -> Path:
    proc = run_pipeline(*ARGS, *extra, artifacts=artifacts, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return newest_run(artifacts)


def newest_run(artifacts: Path) -> Path:
    return max((artifacts / "runs" / "mie_los").iterdir(), key=lambda p: p.stat().st_mtime)


def kill_while(artifacts: Path, mode: str, *extra: str) -> None:
    marker = artifacts / f"stalled-{mode.replace(':', '-')}"
    proc = start_script(ROOT / "tests" / "interrupt_runner.py", mode, str(marker), f"paths.artifacts={artifacts}",
                        *ARGS, *extra, cwd=artifacts, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                        start_new_session=True)
    deadline = time.monotonic() + 120
    while not marker.exists():
        if proc.poll() is not None:
            raise AssertionError(f"the run ended before the stall ({mode}): {proc.stderr.read().decode()[-2000:]}")
        assert time.monotonic() < deadline, f"no stall within 120 s ({mode})"
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL


def assert_no_broken_final_file(artifacts: Path) -> None:
    """Every file under a final name reads whole; only hidden temp files hold partial data."""
    temps = []
    for path in artifacts.rglob("*"):
        if path.is_dir() or "stalled-" in path.name:
            continue
        if path.name.startswith("."):
            temps.append(path)
            continue
        if path.suffix == ".parquet":
            pl.read_parquet(path)                                  # raises on a truncated file
        elif path.suffix == ".rrd":
            from tests.helpers.rrd_reading import read_chunks
            assert read_chunks(path)
    return temps


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    artifacts = tmp_path_factory.mktemp("reference")
    return run(artifacts, "record.enabled=false")


@pytest.mark.parametrize("mode", ["parquet-half:track", "parquet-rename:track", "parquet-half:summary.parquet",
                                  "parquet-rename:scenario"])
def test_a_run_killed_while_writing_parquet_reruns_to_the_same_tables(tmp_path, reference, mode):
    kill_while(tmp_path, mode, "record.enabled=false")
    temps = assert_no_broken_final_file(tmp_path)
    assert temps, "the kill should have left the writer's hidden temp file behind"
    from pipeline.results.query import query
    query("SELECT COUNT(*) AS n FROM summary", root=tmp_path)     # the tables stay queryable
    rerun = run(tmp_path, "record.enabled=false")
    assert_same_tables(reference, rerun)


def test_a_run_killed_while_writing_the_recording_reruns_to_a_complete_one(tmp_path, reference):
    kill_while(tmp_path, "rrd")
    killed = newest_run(tmp_path)
    assert not (killed / "recording.rrd").exists()                 # never a partial .rrd under the final name
    assert assert_no_broken_final_file(tmp_path)
    rerun = run(tmp_path)
    assert_no_broken_final_file(tmp_path)
    from tests.helpers.rrd_reading import read_chunks
    assert read_chunks(rerun / "recording.rrd")
    (rerun / "recording.rrd").unlink()
    assert_same_tables(reference, rerun)
