"""Progress of long stages (pipeline.run.progress): plain lines on a fake clock, the bar, the mode chosen
for a terminal, a pipe and a sweep, and what a real run and a real sweep print (issue 19)."""

from __future__ import annotations

import io
import re
from pathlib import Path

import pytest

from filters.progress import SILENT, current
from pipeline.run.progress import DELAY, INTERVAL, Reporter, Task, choose_mode, duration
from tests.helpers.processes import run_pipeline

ROOT = Path(__file__).resolve().parents[1]


class Clock:
    """Seconds that pass only when the test says so."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now

    def at(self, seconds: float) -> "Clock":
        self.now = 1000.0 + seconds
        return self


def lines_task(clock: Clock, label: str = "[track] AMMPF, variant 1/3", units: int | None = 1) -> tuple[Task, list[str]]:
    out: list[str] = []
    return Task(label, units, mode="lines", clock=clock, emit=out.append), out


def test_plain_lines_come_after_the_delay_then_every_interval_with_the_share_and_eta():
    clock = Clock()
    task, out = lines_task(clock)
    task.start(360, "scan", "AMMPF")
    for second, scans in ((0.5, 30), (1.9, 60)):           # within DELAY: nothing, however often it reports
        clock.at(second)
        task.advance(scans)
    assert out == []
    clock.at(3.0)
    task.advance(30)                                         # 120 of 360 in 3 s: 6 s to go
    assert out == ["[track] AMMPF, variant 1/3: scan 120/360, 33 %, ETA 6 s"]
    for second in (4.0, 8.0, 3.0 + INTERVAL - 0.1):          # until INTERVAL has passed: no new line
        clock.at(second)
        task.advance(10)
    assert len(out) == 1
    clock.at(3.0 + INTERVAL)
    task.advance(120)                                        # 270 of 360 in 13 s
    assert out[1] == "[track] AMMPF, variant 1/3: scan 270/360, 75 %, ETA 4 s"
    assert DELAY == 2.0 and INTERVAL == 10.0


def test_a_stage_within_the_delay_prints_nothing():
    clock = Clock()
    task, out = lines_task(clock)
    task.start(360, "scan", "AMMPF")
    for k in range(360):
        clock.at(k * (DELAY - 0.01) / 360)
        task.advance()
    task.tick()
    task.close()
    clock.at(100.0)
    task.tick()                                              # closed: nothing after the stage either
    assert out == []


def test_chunks_of_runs_and_the_filter_inside_each_give_the_share_of_the_stage():
    clock = Clock()
    task, out = lines_task(clock, units=4)
    task.start(360, "scan", "AMMPF")
    clock.at(4.0)
    task.advance(360)                                        # chunk 1 of 4 in 4 s
    assert out == ["[track] AMMPF, variant 1/3: chunk 1/4, scan 360/360, 25 %, ETA 12 s"]
    task.unit_done()
    task.start(360, "scan", "AMMPF")
    clock.at(4.0 + INTERVAL)
    task.advance(180)                                        # 1.5 of 4 chunks in 14 s
    assert out[1] == "[track] AMMPF, variant 1/3: chunk 2/4, scan 180/360, 38 %, ETA 23 s"


def test_a_stage_nothing_measures_says_how_long_it_has_run():
    clock = Clock()
    task, out = lines_task(clock, "[record] recording.rrd", units=None)
    clock.at(DELAY)
    task.tick()
    task.start(360, "scan", "AMMPF")                         # a filter re-run for the recording
    clock.at(DELAY + INTERVAL)
    task.advance(90)
    assert out == ["[record] recording.rrd: 2 s so far", "[record] recording.rrd: AMMPF scan 90/360, 12 s so far"]
    clock = Clock()
    task, out = lines_task(clock, "[evaluate] 3 variants x 361 steps")
    clock.at(5.0)
    task.set_note("writing its table")
    assert out == ["[evaluate] 3 variants x 361 steps: writing its table, 5 s so far"]


def test_the_bar_is_drawn_after_the_delay_and_cleared_at_the_end():
    clock, stream = Clock(), io.StringIO()
    task = Task("[track] AMMPF, variant 1/3", mode="bar", clock=clock, bar_stream=stream)
    task.start(360, "scan", "AMMPF")
    clock.at(1.0)
    task.advance(100)
    assert stream.getvalue() == ""
    clock.at(3.0)
    task.advance(20)
    drawn = stream.getvalue()
    assert "[track] AMMPF, variant 1/3:  33%|" in drawn and "| scan 120/360, ETA 6 s" in drawn
    task.close()                                             # blanked: the stage's own log line follows
    assert re.fullmatch(r"\r +\r", stream.getvalue()[len(drawn):])


def test_reporter_tasks_listen_to_what_runs_inside_and_off_prints_nothing():
    clock, out = Clock(), []
    reporter = Reporter("lines", clock=clock, emit=out.append, heartbeat=None)
    assert current() is SILENT
    with reporter.task("[track] EKF, variant 3/3") as task:
        assert current() is task
        current().start(10, "scan", "EKF")
        clock.at(DELAY)
        current().advance(5)
    assert current() is SILENT
    assert out == ["[track] EKF, variant 3/3: scan 5/10, 50 %, ETA 2 s"]
    quiet: list[str] = []
    with Reporter("off", clock=clock, emit=quiet.append).task("[evaluate] x") as task:
        task.start(10)
        clock.at(1000.0)
        task.advance(5)
    assert quiet == []


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_the_mode_a_bar_on_a_terminal_lines_in_a_pipe_or_a_sweep():
    assert choose_mode(_Terminal(), multirun=False, environ={}) == "bar"
    assert choose_mode(io.StringIO(), multirun=False, environ={}) == "lines"
    assert choose_mode(_Terminal(), multirun=True, environ={}) == "lines"       # jobs share the terminal
    assert choose_mode(io.StringIO(), multirun=False, environ={"MTT_PROGRESS": "bar"}) == "bar"
    assert choose_mode(_Terminal(), multirun=False, environ={"MTT_PROGRESS": "off"}) == "off"
    assert choose_mode(_Terminal(), multirun=False, environ={"MTT_PROGRESS": "loud"}) == "bar"
    assert [duration(s) for s in (0.4, 28, 99.6, 245, 3725)] == ["0 s", "28 s", "1 min 40 s", "4 min 05 s", "1 h 02 min"]


UNFORCED = {"MTT_PROGRESS": None}       # the child chooses its progress mode by its stderr, as a user's does


LOG_LINE = re.compile(r"^\[\d\d:\d\d:\d\d\] ")


def test_a_real_run_in_a_pipe_prints_log_lines_and_no_bar(tmp_path):
    """stderr a pipe: whatever progress there is comes as plain log lines, never a bar (no carriage
    returns, no bar characters); the summary table on stdout is as before."""
    proc = run_pipeline("experiment=sonobuoy_case2", "mc.runs=2", "++scenario.duration=300", "++target_model.particles=300",
                        "record.enabled=false", artifacts=tmp_path, timeout=300, env=UNFORCED)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "\r" not in proc.stderr and "%|" not in proc.stderr and "\x1b[" not in proc.stderr
    assert all(LOG_LINE.match(line) for line in proc.stderr.splitlines()), proc.stderr
    assert "[job" not in proc.stderr                        # a single run's lines name no job
    for line in proc.stderr.splitlines():                    # a progress line, if the machine was slow enough
        if re.search(r"\] \[(track|evaluate|record)\] .*: .*(ETA|so far)", line):
            assert re.search(r"(\d+ %, ETA|so far)", line), line
    assert proc.stdout.startswith("sonobuoy_case2: 2 Monte Carlo runs")


@pytest.mark.full
@pytest.mark.parametrize("launcher", ["joblib", "isolated"])
def test_a_sweeps_lines_and_tables_name_their_job(tmp_path, launcher):
    """Two jobs at once on one terminal: every log line of a job carries "[job N]", and each job's
    printed summary is headed by its job number and its overrides."""
    proc = run_pipeline("-m", "mc.runs=2", "scenario.steps=30", "record.enabled=false", "variants=[fsimm]", "mc.seed=1,2",
                        f"hydra/launcher={launcher}", "hydra.launcher.n_jobs=2", artifacts=tmp_path, timeout=300,
                        env=UNFORCED)
    assert proc.returncode == 0, proc.stderr[-3000:]
    job_lines = [line for line in proc.stderr.splitlines() if LOG_LINE.match(line)]
    assert job_lines and all(re.match(r"^\[\d\d:\d\d:\d\d\] \[job [01]\] ", line) for line in job_lines), job_lines
    for job in (0, 1):
        assert any(line.startswith(f"[{line[1:9]}] [job {job}] experiment ao_vsimm_s1") for line in job_lines)
        (header,) = [line for line in proc.stdout.splitlines() if line.startswith(f"[job {job}] ao_vsimm_s1: ")]
        assert header.startswith(f"[job {job}] ao_vsimm_s1: 2 Monte Carlo runs; overrides: paths.artifacts={tmp_path} "
                                 f"mc.runs=2 scenario.steps=30 ") and header.endswith(f" mc.seed={job + 1}"), header
        (report,) = tmp_path.glob(f"multirun/*/{job}/report.txt")
        assert report.read_text().startswith(header + "\n")


# ---- the filters' side: every study's filters report their scans, and listening changes nothing ---
class Heard:
    """A filters.progress listener keeping what it hears (thread-safe: particle chunks report in threads)."""

    def __init__(self) -> None:
        import threading
        self.lock, self.starts, self.done = threading.Lock(), [], []

    def start(self, total, unit="step", label=None):
        with self.lock:
            self.starts.append((total, unit, label))
            self.done.append(0.0)

    def advance(self, amount=1.0):
        with self.lock:
            self.done[-1] += amount


@pytest.mark.parametrize("length", [0, 1, 999, 1000, 2500, 10_001])
def test_counted_is_the_range_and_its_steps_add_up(length):
    from filters.progress import counted, listening
    assert list(counted(range(3, 3 + length))) == list(range(3, 3 + length))     # nobody listening
    heard = Heard()
    with listening(heard):
        steps = list(counted(range(3, 3 + length), "scan", "F"))
    assert steps == list(range(3, 3 + length))
    assert heard.starts == [(length, "scan", "F")] and heard.done == [length]


def _assert_same(a, b, where: str) -> None:
    """Two filter results equal to the bit, field by field (dataclasses, mappings, arrays), their
    compute time aside."""
    import dataclasses

    import numpy as np
    if dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            if f.name != "compute_seconds":
                _assert_same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, dict) or hasattr(a, "keys"):
        assert list(a.keys()) == list(b.keys()), where
        for name in a:
            _assert_same(a[name], b[name], f"{where}[{name}]")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _assert_same(x, y, f"{where}[{i}]")
    else:
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=where)


def _smoke_cases() -> list:
    from tests.helpers.config import smoke_experiments
    return [pytest.param(name, overrides, id=name) for name, overrides in smoke_experiments()]


@pytest.mark.parametrize("experiment, overrides", _smoke_cases())
def test_every_studys_filters_report_their_scans_and_listening_changes_nothing(experiment, overrides):
    """Each variant of each study (its smoke run, 3 runs) filtered with nobody listening and with a
    listener: the same estimate to the bit; what it heard adds up to the scans it announced, named
    by the filter."""
    from hydra import compose, initialize_config_dir

    from filters.progress import listening
    from pipeline.run.runner import prepare
    with initialize_config_dir(version_base="1.3", config_dir=str(ROOT / "conf")):
        cfg = compose("config", overrides=[f"experiment={experiment}", "mc.runs=3", *overrides])
    prepared = prepare(cfg)
    truth = prepared.scenario.generate(3, 1)
    detections = prepared.sensor.measure(truth, 1)
    view = prepared.study.track_input(truth, detections, prepared.sensor, 1)
    for key, estimator in prepared.estimators.items():
        quiet = estimator.run(view)
        heard = Heard()
        with listening(heard):
            loud = estimator.run(view)
        _assert_same(quiet, loud, f"{experiment}: {key}")
        assert heard.starts, f"{experiment}: {key} reported nothing"
        assert all(label == estimator.name and unit == "scan" for _, unit, label in heard.starts), heard.starts
        assert [pytest.approx(total) for total, _, _ in heard.starts] == heard.done, (key, heard.starts, heard.done)
