"""Sweeps through Hydra's submitit launcher (the ``[slurm]`` extra): conf/hydra/launcher/slurm.yaml
composes with the plugin's SLURM node, and the same launcher's local executor (submitit_local: each
job a process of its own, pickled and started as on a cluster node) runs a two-job sweep into the
usual layout, with the sweep summary written by the submitting process's callback."""

from __future__ import annotations

import json
from pathlib import Path

import polars as pl
import pytest
from hydra import compose, initialize_config_dir

from tests.helpers.extras import require_extra
from tests.helpers.processes import run_module

# .ci/run sets MTT_REQUIRE_SLURM=1: in CI a missing extra fails instead of skipping
require_extra("slurm", "hydra_plugins.hydra_submitit_launcher", "submitit")

ROOT = Path(__file__).resolve().parents[1]
# full tier (tests/helpers/tiers.py): the submitit launcher
pytestmark = [pytest.mark.slurm, pytest.mark.full]


def test_the_slurm_launcher_config_composes_with_overridable_resources():
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        cfg = compose("config", overrides=["hydra/launcher=slurm", "hydra.launcher.partition=short"],
                      return_hydra_config=True)
    launcher = cfg.hydra.launcher
    assert launcher._target_ == "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"
    assert launcher.partition == "short" and launcher.account is None
    assert (launcher.timeout_min, launcher.cpus_per_task, launcher.mem_gb, launcher.max_num_timeout) == (120, 1, 4, 0)
    assert launcher.name == "mtt-sweep" and list(launcher.setup) == []


def test_a_two_job_sweep_through_submitit_local_lands_in_the_artifacts_with_its_summary(tmp_path):
    # relative paths.artifacts, started from tmp_path: resolved against where the sweep started
    proc = run_module(
        "pipeline", "-m", "experiment=ao_vsimm_s1", "mc.runs=2", "mc.seed=1,2",
        "scenario.steps=60", "record.enabled=false", "paths.artifacts=artifacts", "hydra/launcher=submitit_local",
        cwd=tmp_path, timeout=180, env={"HYDRA_FULL_ERROR": "1"})
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-4000:]
    assert "Submitit 'local' sweep output dir" in proc.stdout and "2 jobs, 2 ok, 0 failed" in proc.stderr

    (sweep,) = (tmp_path / "artifacts" / "multirun").iterdir()
    status = [json.loads((sweep / job / "status.json").read_text()) for job in ("0", "1")]
    assert [(s["status"], s["job_num"]) for s in status] == [("ok", 0), ("ok", 1)], status
    assert status[0]["process"]["pid"] != status[1]["process"]["pid"]     # each job in a process of its own
    for job in ("0", "1"):
        for name in ("summary.parquet", "metrics.parquet", "estimates/vsimm.parquet", ".hydra/config.yaml"):
            assert (sweep / job / name).is_file(), (job, name)
    summary = pl.read_parquet(sweep / "sweep_summary.parquet")          # the submitting process's callback
    assert summary["job_num"].unique().sort().to_list() == [0, 1]
    assert summary["mc.seed"].unique().sort().to_list() == [1, 2] and set(summary["status"]) == {"ok"}
    # submitit keeps each job's own stdout/stderr under the (absolute, pinned) sweep folder
    logs = "".join(p.read_text() for p in sweep.glob(".submitit/*/*_log.err"))
    assert "2 Monte Carlo runs, seed 1," in logs and "2 Monte Carlo runs, seed 2," in logs
