"""A sweep through Hydra's Ray launcher on a local Ray instance (the ``[distributed]`` extra).

One test, one two-job sweep (Ray's start costs most of its time): the jobs run as Ray tasks in
Ray worker processes, land in the usual ``<artifacts>/multirun/<time>/<job>/`` layout, the
sweep summary is written by the driver's callback, and ``pipeline.results.query`` finds both jobs.
Skipped when ray or hydra-ray-launcher is not installed (``pip install -e '.[test,distributed]'``).
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import pytest

from tests.helpers.extras import require_extra

# .ci/run sets MTT_REQUIRE_DISTRIBUTED=1: in CI a missing extra fails instead of skipping
require_extra("distributed", "hydra_plugins.hydra_ray_launcher", "ray")

from pipeline.results.query import query  # noqa: E402  (after the skip: the module needs nothing of Ray)
from tests.helpers.processes import run_module

ROOT = Path(__file__).resolve().parents[1]
# full tier (tests/helpers/tiers.py): the Ray launcher
pytestmark = [pytest.mark.distributed, pytest.mark.full]


@pytest.fixture
def ray_temp_dir():
    # Ray's session folder holds unix sockets, whose paths must stay under ~107 characters: a
    # short folder in /tmp, not pytest's long tmp_path; removed afterwards
    path = tempfile.mkdtemp(prefix="mtt-ray-", dir="/tmp")
    yield path
    shutil.rmtree(path, ignore_errors=True)


def test_a_two_job_sweep_through_the_ray_launcher_lands_in_the_artifacts_and_is_queryable(tmp_path, ray_temp_dir):
    # relative paths.artifacts, started from tmp_path: resolved against where the sweep started
    proc = run_module(
        "pipeline", "-m", "experiment=ao_vsimm_s1", "mc.runs=2", "mc.seed=1,2",
        "record.enabled=false", "paths.artifacts=artifacts", "hydra/launcher=ray_local",
        "hydra.launcher.ray.init.num_cpus=2", f"++hydra.launcher.ray.init._temp_dir={ray_temp_dir}",
        cwd=tmp_path, timeout=300, env={"HYDRA_FULL_ERROR": "1", "RAY_USAGE_STATS_ENABLED": "0"})
    output = proc.stdout + proc.stderr
    assert proc.returncode == 0, output[-4000:]
    assert "Ray Launcher is launching 2 jobs" in output
    # the jobs ran in Ray worker processes: their progress lines are in the workers' own log files
    # (the copies Ray forwards to the driver's terminal arrive asynchronously; not relied on here)
    worker_logs = "".join(p.read_text() for p in Path(ray_temp_dir).glob("session_2*/logs/worker-*.err"))
    assert "2 Monte Carlo runs, seed 1," in worker_logs and "2 Monte Carlo runs, seed 2," in worker_logs

    artifacts = tmp_path / "artifacts"
    (sweep,) = (artifacts / "multirun").iterdir()
    for job in ("0", "1"):
        status = json.loads((sweep / job / "status.json").read_text())
        assert status["status"] == "ok" and status["job_num"] == int(job), status
        assert status["run_id"] == f"multirun/{sweep.name}/{job}"
        for name in ("summary.parquet", "metrics.parquet", "truth.parquet", "estimates/ao_vsimm.parquet",
                     ".hydra/config.yaml"):
            assert (sweep / job / name).is_file(), (job, name)
    assert (sweep / "sweep_summary.parquet").is_file()          # the driver's SweepSummary callback
    assert len(list((artifacts / "cache" / "scenario").glob("*.parquet"))) == 2   # one per seed, same cache

    jobs = query('SELECT run_id, status, "mc.seed", COUNT(*) AS n_rows FROM summary GROUP BY ALL ORDER BY ALL',
                 root=artifacts)
    assert jobs["run_id"].to_list() == [f"multirun/{sweep.name}/0", f"multirun/{sweep.name}/1"]
    assert jobs["status"].to_list() == ["ok", "ok"] and jobs["mc.seed"].to_list() == [1, 2]
    assert jobs["n_rows"].min() > 0
    runs = query("SELECT run_id, kind, sweep, status FROM runs ORDER BY run_id", root=artifacts)
    assert runs["kind"].to_list() == ["multirun", "multirun"] and runs["status"].to_list() == ["ok", "ok"]
    assert runs["sweep"].to_list() == [f"multirun/{sweep.name}"] * 2
