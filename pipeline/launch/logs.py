"""What every console log line of a job says about which job it is.

In a sweep (Hydra's MULTIRUN) the jobs' lines share one terminal, interleaved; ``JobTag`` gives each
record ``job`` = `` [job 3]`` there and ``""`` in a single run, for the console format of
conf/hydra/job_logging/pipeline.yaml (``[%(asctime)s]%(job)s %(message)s``). Hydra's job logging
config builds it with the job's own ``hydra.mode`` and ``hydra.job.num``, in whatever process runs
the job (the joblib, isolated and Ray launchers all configure the job's logging there).
"""

from __future__ import annotations

import logging
from typing import Any


class JobTag(logging.Filter):
    def __init__(self, mode: Any = None, num: Any = None) -> None:
        super().__init__()
        multirun = str(getattr(mode, "name", mode)).upper().endswith("MULTIRUN")
        self.tag = f" [job {num}]" if multirun and num is not None else ""

    def filter(self, record: logging.LogRecord) -> bool:
        record.job = self.tag
        return True
