"""One sweep job in a fresh interpreter: ``python -m hydra_plugins.isolated_launcher._job_process RESULT``
reads the job from stdin and writes its pickled JobReturn to RESULT. (The leading ``_`` keeps Hydra's
plugin scan, which imports every other module under hydra_plugins at each start, away from it.)

A fresh interpreter, not a fork of the launcher: a fork would copy the parent's thread pools
(polars, BLAS) in whatever state they were, which can deadlock the child. The job's arguments
travel as cloudpickle bytes, as they do to joblib's loky workers.
"""

from __future__ import annotations

import os
import pickle
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.core.singleton import Singleton
from hydra.core.utils import JobReturn, JobStatus, run_job, setup_globals
from hydra.types import HydraContext, TaskFunction
import cloudpickle
from omegaconf import DictConfig, open_dict


def execute_job(job_num: int, overrides: Sequence[str], hydra_context: HydraContext, config: DictConfig,
                task_function: TaskFunction, singleton_state: dict[Any, Any]) -> JobReturn:
    """Run one job as hydra-joblib-launcher's execute_job does: the job's own config (the sweep's
    overrides + its own), its num and id, HydraConfig set, and run_job for the output folder and
    the on_job_start/on_job_end callbacks."""
    setup_globals()
    Singleton.set_state(singleton_state)
    sweep_config = hydra_context.config_loader.load_sweep_config(config, list(overrides))
    with open_dict(sweep_config):
        sweep_config.hydra.job.id = f"{sweep_config.hydra.job.name}_{job_num}"
        sweep_config.hydra.job.num = job_num
    HydraConfig.instance().set_config(sweep_config)
    return run_job(hydra_context=hydra_context, config=sweep_config, task_function=task_function,
                   job_dir_key="hydra.sweep.dir", job_subdir_key="hydra.sweep.subdir")


def write_result(job_return: JobReturn, result_path: Path) -> None:
    """Pickle the JobReturn to a temp file renamed onto ``result_path``: a process killed while
    writing leaves no result, so the launcher counts it as died, never reads half a result."""
    try:
        data = cloudpickle.dumps(job_return)
    except Exception as exc:      # an unpicklable return value (or exception): say so instead
        job_return.return_value = RuntimeError(f"the job's return value could not be pickled: {exc!r}")
        job_return.status = JobStatus.FAILED
        data = cloudpickle.dumps(job_return)
    partial = result_path.with_name(result_path.name + ".partial")
    partial.write_bytes(data)
    os.replace(partial, result_path)


def main(result_path: Path) -> None:
    # (the launcher's sys.path, the sweep's shared arguments as cloudpickle bytes, job num, overrides)
    sys_path, shared, job_num, overrides = pickle.load(sys.stdin.buffer)
    sys.path[:] = sys_path + [p for p in sys.path if p not in sys_path]   # import what the launcher could
    hydra_context, config, task_function, singleton_state = cloudpickle.loads(shared)
    write_result(execute_job(job_num, overrides, hydra_context, config, task_function, singleton_state), result_path)


if __name__ == "__main__":
    main(Path(sys.argv[1]))
