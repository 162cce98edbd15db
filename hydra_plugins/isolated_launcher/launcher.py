"""IsolatedLauncher: each job of a sweep in its own fresh process, at most ``n_jobs`` at a time.

A job whose process dies without a result (killed by a signal, or exited early) fails that job
only: the launcher builds the job's config as the job would have, hands Hydra's on_job_end
callbacks a FAILED JobReturn saying how the process ended (the project's SweepSummary callback
records it as the job's failure: status.json and a failed summary row), and the other jobs go on.
"""

# no `from __future__ import annotations`: Hydra's plugin scan runs this module outside sys.modules,
# where @dataclass cannot resolve string annotations
import contextlib
import copy
import logging
import os
import pickle
import queue
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.core.singleton import Singleton
from hydra.core.utils import JobReturn, JobStatus, configure_log, filter_overrides, setup_globals
from hydra.plugins.launcher import Launcher
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig, OmegaConf, open_dict, read_write

log = logging.getLogger(__name__)


class JobProcessDied(RuntimeError):
    """A job's process ended without handing back a result: the job failed, not the sweep."""

    def __init__(self, message: str, peak_rss_mb: float | None = None) -> None:
        super().__init__(message)
        self.peak_rss_mb = peak_rss_mb      # the job's process's, for its status (not the launcher's)


@dataclass
class DeadJobReturn(JobReturn):
    """FAILED, yet reading ``return_value`` gives None instead of raising the error.

    Hydra's BasicSweeper reads every job's return_value right after the launch to re-raise a
    job's exception, which would abort the sweep before on_multirun_end (the sweep summary). The
    error stays in ``_return_value`` for the on_job_end callbacks; the sweep goes on, as it does
    for a job whose task function records its own failure and returns.
    """

    @property  # type: ignore[override]
    def return_value(self) -> Any:
        return None

    @return_value.setter
    def return_value(self, value: Any) -> None:
        self._return_value = value


@dataclass
class ProcessOutcome:
    """How one job's process ended: its exit code (-N: killed by signal N) and its result, if any."""

    exit_code: int
    result: bytes | None
    seconds: float
    peak_rss_mb: float


def jobs_at_a_time(n_jobs: int) -> int:
    """joblib's convention: n_jobs > 0 is that many; -1 is one per CPU, -2 all but one, ...

    The CPUs are joblib's count (it reads the process's affinity and a container's CPU quota), the
    one the joblib launcher uses, so ``n_jobs=-1`` means the same under both launchers."""
    if n_jobs == 0:
        raise ValueError("hydra.launcher.n_jobs: 0 runs nothing; give a positive count or -1 (one per CPU)")
    if n_jobs > 0:
        return n_jobs
    from joblib import cpu_count        # here, not at import: Hydra's plugin scan imports this module in every job
    return max(1, cpu_count() + 1 + n_jobs)


def describe_death(outcome: ProcessOutcome) -> str:
    """The error a dead job's status.json carries: what ended the process, when, at what memory."""
    if outcome.exit_code < 0:
        number = -outcome.exit_code
        try:
            name = signal.Signals(number).name
        except ValueError:
            name = "unknown signal"
        why = "; the out-of-memory killer sends this" if number == signal.SIGKILL else ""
        ended = f"was killed by signal {number} ({name}{why})"
    else:
        ended = f"exited with code {outcome.exit_code} without a result (its output above says why)"
    return f"the job's process {ended} after {outcome.seconds:.1f} s, at a peak of {outcome.peak_rss_mb:.0f} MB"


class JobProcess:
    """One job's process, started from the launcher's main thread, and a thread that feeds it its job
    and waits for it to end, then puts ``(position, ProcessOutcome)`` on ``ended``.

    os.wait4 (not Popen.wait) so the outcome carries the process's own peak memory: for a job the
    out-of-memory killer ended, that is the number to look at.
    """

    def __init__(self, position: int, job_input: bytes, result_path: Path, ended: "queue.SimpleQueue[Any]") -> None:
        self.position, self.result_path, self.ended = position, result_path, ended
        self.started = time.monotonic()
        self.process = subprocess.Popen([sys.executable, "-m", f"{__package__}._job_process", str(result_path)],
                                        stdin=subprocess.PIPE)
        self.thread = threading.Thread(target=self._feed_and_wait, args=(job_input,), daemon=True,
                                       name=f"job-process-{position}")
        self.thread.start()

    def _feed_and_wait(self, job_input: bytes) -> None:
        try:
            assert self.process.stdin is not None
            with contextlib.suppress(BrokenPipeError):    # it died before reading its job: its exit code says how
                self.process.stdin.write(job_input)
            with contextlib.suppress(BrokenPipeError):
                self.process.stdin.close()
            # usage.ru_maxrss: the job's peak, or the launcher's if larger (Linux carries the parent's
            # high-water mark across the vfork and exec that started it); a job writes its own (VmHWM)
            _, wait_status, usage = os.wait4(self.process.pid, 0)
            self.process.returncode = os.waitstatus_to_exitcode(wait_status)
            result = self.result_path.read_bytes() if self.result_path.exists() else None
            self.ended.put((self.position, ProcessOutcome(self.process.returncode, result,
                                                          time.monotonic() - self.started, usage.ru_maxrss / 1024.0)))
        except BaseException as exc:  # the launcher re-raises it: never leave it waiting for this job
            self.ended.put((self.position, exc))

    def stop(self) -> None:
        """End the job's process (the sweep was interrupted) and wait for it."""
        if self.process.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.process.pid, signal.SIGTERM)
        self.thread.join()


def next_ended(ended: "queue.SimpleQueue[Any]") -> Any:
    """The next ``(position, outcome)`` a job's thread puts. Waits in short slices: a Ctrl-C that another
    thread takes (polars and jemalloc start their own) reaches the main thread only when it wakes."""
    while True:
        try:
            return ended.get(timeout=0.2)
        except queue.Empty:
            pass


class IsolatedLauncher(Launcher):
    def __init__(self, n_jobs: int = -1) -> None:
        self.n_jobs = n_jobs
        self.config: DictConfig | None = None
        self.task_function: TaskFunction | None = None
        self.hydra_context: HydraContext | None = None

    def setup(self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig) -> None:
        self.config = config
        self.task_function = task_function
        self.hydra_context = hydra_context

    def launch(self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int) -> Sequence[JobReturn]:
        """Run the jobs, each in its own process; return their JobReturns in the order given."""
        setup_globals()
        assert self.config is not None and self.task_function is not None and self.hydra_context is not None
        configure_log(self.config.hydra.hydra_logging, self.config.hydra.verbose)
        sweep_dir = Path(str(self.config.hydra.sweep.dir))
        sweep_dir.mkdir(parents=True, exist_ok=True)
        at_a_time = jobs_at_a_time(self.n_jobs)
        log.info(f"Isolated launcher: {len(job_overrides)} jobs, each in its own process, {at_a_time} at a time")
        log.info(f"Launching jobs, sweep output dir : {sweep_dir}")
        for position, overrides in enumerate(job_overrides):
            log.info(f"\t#{initial_job_idx + position} : {' '.join(filter_overrides(overrides))}")

        # pickled once for all jobs; each job's input adds its num and overrides. cloudpickle, not
        # pickle: the task function is the app's decorated main, which pickle cannot send by value
        import cloudpickle       # here, not at import: Hydra's plugin scan imports this module in every job
        shared = cloudpickle.dumps((self.hydra_context, self.config, self.task_function, Singleton.get_state()))
        returns: list[JobReturn | None] = [None] * len(job_overrides)
        waiting = deque(range(len(job_overrides)))
        running: dict[int, JobProcess] = {}
        ended: queue.SimpleQueue[tuple[int, ProcessOutcome | BaseException]] = queue.SimpleQueue()
        with tempfile.TemporaryDirectory(prefix="hydra-isolated-") as results_dir:
            try:
                while waiting or running:
                    # jobs start only here, in the main thread: after a Ctrl-C (raised here) none does
                    while waiting and len(running) < at_a_time:
                        position = waiting.popleft()
                        job_input = pickle.dumps((list(sys.path), shared, initial_job_idx + position,
                                                  list(job_overrides[position])))
                        running[position] = JobProcess(position, job_input, Path(results_dir) / f"{position}.pkl",
                                                       ended)
                    position, outcome = next_ended(ended)
                    running.pop(position).thread.join()
                    if isinstance(outcome, BaseException):
                        raise outcome
                    returns[position] = self._job_return(initial_job_idx + position, job_overrides[position], outcome)
            finally:              # interrupted, or the launcher failed: end the jobs still running
                for job in running.values():
                    job.stop()
        assert all(isinstance(r, JobReturn) for r in returns)
        return returns  # type: ignore[return-value]

    def _job_return(self, job_num: int, overrides: Sequence[str], outcome: ProcessOutcome) -> JobReturn:
        if outcome.result is not None:
            try:
                import cloudpickle
                job_return = cloudpickle.loads(outcome.result)
                assert isinstance(job_return, JobReturn)
                return job_return
            except Exception as exc:
                error = f"the job's result could not be read back: {exc!r}"
        else:
            error = describe_death(outcome)
        log.error(f"job #{job_num} ({' '.join(filter_overrides(overrides))}) failed: {error}")
        return self._report_dead_job(job_num, overrides, JobProcessDied(error, outcome.peak_rss_mb))

    def _report_dead_job(self, job_num: int, overrides: Sequence[str], error: JobProcessDied) -> JobReturn:
        """The FAILED JobReturn run_job would have built, handed to the on_job_end callbacks here,
        in the launcher's process, since the job's own process cannot any more."""
        assert self.config is not None and self.hydra_context is not None
        sweep_config = self.hydra_context.config_loader.load_sweep_config(self.config, list(overrides))
        with open_dict(sweep_config):
            sweep_config.hydra.job.id = f"{sweep_config.hydra.job.name}_{job_num}"
            sweep_config.hydra.job.num = job_num
        previous_hydra_config = HydraConfig.instance().cfg
        HydraConfig.instance().set_config(sweep_config)
        try:
            output_dir = Path(str(sweep_config.hydra.sweep.dir)) / str(sweep_config.hydra.sweep.subdir)
            with read_write(sweep_config.hydra.runtime), open_dict(sweep_config.hydra.runtime):
                sweep_config.hydra.runtime.output_dir = str(output_dir.absolute())
            HydraConfig.instance().set_config(sweep_config)
            output_dir.mkdir(parents=True, exist_ok=True)
            task_config = copy.deepcopy(sweep_config)
            with read_write(task_config), open_dict(task_config):
                del task_config["hydra"]
            job_return = DeadJobReturn(
                overrides=list(OmegaConf.to_container(sweep_config.hydra.overrides.task)),  # type: ignore[arg-type]
                cfg=task_config, hydra_cfg=copy.deepcopy(HydraConfig.instance().cfg),
                working_dir=str(output_dir) if sweep_config.hydra.job.chdir else os.getcwd(),
                task_name=str(sweep_config.hydra.job.name), status=JobStatus.FAILED,
                _return_value=error)
            self.hydra_context.callbacks.on_job_end(config=sweep_config, job_return=job_return)
            return job_return
        finally:
            HydraConfig.instance().cfg = previous_hydra_config  # type: ignore[assignment]
