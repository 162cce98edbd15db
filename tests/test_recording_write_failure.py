"""A recording that cannot be written (issue 16 item 7): under a file-size limit the job used to
block forever in Rerun's flush and stay ``running``. It must end ``failed`` within seconds, with
the OS error and the file named, and leave no partial file under the final name nor a temp file.

The limit (RLIMIT_FSIZE, set in the child only) is above every Parquet table of a 2-run
``ao_vsimm_s1`` job (at most 100 KB) and below its recording (1.4 MB; 2.8 MB with two recorded
runs). With Rerun's file sink the three limits gave: "File-writer thread shut down prematurely"
(no OS error); a hang in flush about one time in two; status ok with a truncated recording.rrd."""

from __future__ import annotations

import json
import resource
import subprocess
from pathlib import Path

import pytest

from tests.helpers.processes import run_pipeline

# full tier (tests/helpers/tiers.py): jobs under a file-size limit in their own processes
pytestmark = pytest.mark.full

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("limit_kb, extra", [(512, []), (1000, []), (2000, ["record.runs=[0,1]"])])
def test_a_recording_over_the_file_size_limit_fails_the_job_within_seconds(tmp_path, limit_kb, extra):
    def limit_file_size() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_kb * 1024, limit_kb * 1024))

    try:
        proc = run_pipeline("experiment=ao_vsimm_s1", "mc.runs=2", *extra, artifacts=tmp_path, timeout=30,
                            preexec_fn=limit_file_size)
    except subprocess.TimeoutExpired:
        pytest.fail("the job hung writing the recording (killed after 30 s)")
    assert proc.returncode != 0, proc.stderr[-2000:]

    (run_dir,) = (tmp_path / "runs" / "ao_vsimm_s1").iterdir()
    status = json.loads((run_dir / "status.json").read_text())
    assert status["status"] == "failed"
    assert "File too large" in status["error"] and "recording.rrd" in status["error"], status["error"]
    assert "File too large" in proc.stderr and "recording.rrd" in proc.stderr
    assert (run_dir / "metrics.parquet").is_file()         # the tables before it were written
    assert not (run_dir / "recording.rrd").exists()
    assert not [p for p in tmp_path.rglob("*") if p.name.endswith(".tmp")], "temporary file left behind"


def test_a_failure_that_cannot_be_recorded_still_reports_the_job_error(tmp_path, caplog):
    """record_failure on the disk that failed the job can fail too: it is logged, never raised over
    the job's own error (which the entry point prints next)."""
    from omegaconf import OmegaConf

    from pipeline.__main__ import _fail
    from pipeline.run.runner import RunContext

    blocked = tmp_path / "run"
    blocked.write_text("")                       # a file where the run folder should be: every write fails
    _fail(RunContext(blocked, tmp_path, []), OmegaConf.create({"experiment_name": "x"}), "the job's error", None)
    assert "could not record the failure" in caplog.text
