"""Progress of the long stages: a bar on a terminal, a plain log line every ``INTERVAL`` s elsewhere
(stderr a pipe or a file, or any job of a sweep), nothing at all for a stage done within ``DELAY`` s.

The runner opens a ``Reporter.task`` around each stage it computes (a cache hit is instant). A task
counts the stage's own units (its chunks of runs, ``mc.chunk_runs``) and listens, through
``filters.progress``, to what the code it runs reports inside a unit (a particle filter's scans,
the bootstrap's metrics); from the two it gives the share done and the time left::

    [12:00:31] [track] AMMPF, variant 1/3: scan 120/360, 33 %, ETA 28 s

A stage that reports nothing inside shows how long it has run instead. The output only reads the
clock and the counts: what the stages compute does not depend on it (no arithmetic, chunking or
random stream is touched).

``MTT_PROGRESS=bar|lines|off`` overrides the choice (e.g. ``lines`` on a terminal, ``off`` anywhere).
The bar is tqdm's: a small library with no dependencies of its own, whose ``write`` clears and
redraws the bar around each log line (``tqdm.contrib.logging``) so lines and bar never mix.
"""

from __future__ import annotations

import functools
import logging
import os
import sys
import threading
import time
from contextlib import ExitStack, contextmanager
from typing import Any, Callable, Iterator, Mapping, TextIO

from filters.progress import listening

log = logging.getLogger("pipeline")

DELAY = 2.0          # s: a stage done sooner shows nothing
INTERVAL = 10.0      # s between two plain lines of one stage
HEARTBEAT = 0.25     # s between the heartbeat's looks at the clock (bar refresh; a line when one is due)
REFRESH = 0.1        # s: the bar is redrawn at most this often
MODES = ("bar", "lines", "off")
ENV = "MTT_PROGRESS"


def choose_mode(stream: Any, multirun: bool, environ: Mapping[str, str] = os.environ) -> str:
    """``bar`` when ``stream`` is a terminal and this is a single run, ``lines`` otherwise (a pipe,
    a file, a sweep job: jobs share a terminal, where bars of several processes would garble each
    other); ``$MTT_PROGRESS`` overrides."""
    forced = environ.get(ENV, "").strip().lower()
    if forced in MODES:
        return forced
    if forced:
        log.warning("%s=%s is not one of %s; choosing by the terminal", ENV, forced, "|".join(MODES))
    if multirun:
        return "lines"
    try:
        tty = bool(stream.isatty())
    except (AttributeError, ValueError, OSError):    # no isatty, or a closed stream
        tty = False
    return "bar" if tty else "lines"


def duration(seconds: float) -> str:
    """'28 s', '4 min 05 s', '1 h 02 min'."""
    s = max(0, round(seconds))
    if s < 100:
        return f"{s} s"
    m, s = divmod(s, 60)
    if m < 60:
        return f"{m} min {s:02d} s"
    h, m = divmod(m, 60)
    return f"{h} h {m:02d} min"


class Task:
    """One stage's progress. ``units``: the stage's own units (its chunks of runs), counted by the
    runner with ``unit_done()``; None when their number is unknown (the recording). Inside a unit,
    whatever runs reports through the filters.progress protocol (``start``, ``advance``; thread-safe).

    ``mode`` bar | lines | off; ``clock`` gives seconds (a fake one in tests); ``emit(text)`` takes
    a plain line; ``bar_stream`` is where a bar is drawn."""

    def __init__(self, label: str, units: int | None = 1, unit: str = "chunk", *, mode: str = "lines",
                 clock: Callable[[], float] = time.monotonic, emit: Callable[[str], None] | None = None,
                 bar_stream: TextIO | None = None) -> None:
        if mode not in MODES:
            raise ValueError(f"progress mode {mode!r}: one of {MODES}")
        self.label, self.units, self.unit, self.mode = label, units, unit, mode
        self.clock = clock
        self.emit = emit or (lambda text: log.info("%s", text))
        self.bar_stream = bar_stream
        self.started = clock()
        self.done_units = 0
        self.inner_total: float | None = None
        self.inner_done = 0.0
        self.inner_unit = ""
        self.inner_label: str | None = None
        self.note: str | None = None
        self.reference: tuple[float, float] | None = None     # (time, fraction) the rate is measured from
        self.lines = 0                                         # plain lines emitted
        self._due = self.started + DELAY                       # when tick has something to show
        self._bar: Any = None
        self._closed = False
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._heart: threading.Thread | None = None

    # ---- filters.progress.Progress: what the running code reports -----------------------------
    def start(self, total: float, unit: str = "step", label: str | None = None) -> None:
        with self._lock:
            self.inner_total = float(total) if total and total > 0 else None
            self.inner_done, self.inner_unit, self.inner_label, self.note = 0.0, unit, label, None
            if self.reference is None:          # the rate from the first report on (setup excluded)
                self.reference = (self.clock(), self.fraction() or 0.0)
        self.tick()

    def advance(self, amount: float = 1.0) -> None:
        with self._lock:
            self.inner_done += amount
        if self.clock() >= self._due:           # called every scan: only a clock read until output is due
            self.tick()

    # ---- the runner's side ----------------------------------------------------------------------
    def unit_done(self) -> None:
        """One of the stage's own units (a chunk of runs) is done."""
        with self._lock:
            self.done_units += 1
            self.inner_total, self.inner_done, self.note = None, 0.0, None
            if self.reference is None:
                self.reference = (self.started, 0.0)
        self.tick()

    def set_note(self, note: str | None) -> None:
        """What the stage does now that no count measures (e.g. writing its table)."""
        with self._lock:
            self.note = note
        self.tick()

    def fraction(self) -> float | None:
        """The share of the stage done, or None when nothing measures it."""
        inner = min(self.inner_done / self.inner_total, 1.0) if self.inner_total else None
        if self.units is None or (self.units <= 1 and inner is None):
            return None
        return min((self.done_units + (inner or 0.0)) / max(self.units, 1), 1.0)

    def eta(self, now: float) -> float | None:
        f = self.fraction()
        if f is None or self.reference is None or self.note is not None:
            return None
        t0, f0 = self.reference
        if f <= f0 or now <= t0:
            return None
        return (1.0 - f) * (now - t0) / (f - f0)

    def describe(self, now: float, with_percent: bool = True) -> str:
        """``label: chunk 2/5, scan 120/360, 43 %, ETA 28 s`` (what is known of it)."""
        parts = []
        if self.units is not None and self.units > 1:
            parts.append(f"{self.unit} {min(self.done_units + 1, self.units)}/{self.units}")
        if self.note:
            parts.append(self.note)
        elif self.inner_total:
            who = f"{self.inner_label} " if self.inner_label and self.inner_label not in self.label else ""
            done = min(int(self.inner_done + 1e-6), int(self.inner_total))
            parts.append(f"{who}{self.inner_unit} {done}/{int(self.inner_total)}")
        f, eta = self.fraction(), self.eta(now)
        if f is not None and with_percent:
            parts.append(f"{100 * f:.0f} %")
        parts.append(f"ETA {duration(eta)}" if eta is not None else f"{duration(now - self.started)} so far")
        return f"{self.label}: {', '.join(parts)}"

    def tick(self) -> None:
        """Show what is due now: nothing before DELAY; then a line every INTERVAL, or the bar redrawn."""
        if self.mode == "off" or self._closed:
            return
        now = self.clock()
        if now < self._due:
            return
        with self._lock:
            if self._closed or now < self._due:
                return
            if self.mode == "lines":
                self._due = now + INTERVAL
                self.lines += 1
                self.emit(self.describe(now))
            else:
                self._due = now + REFRESH
                self._draw(now)

    def _draw(self, now: float) -> None:
        f = self.fraction()
        info = self.describe(now, with_percent=False)[len(self.label) + 2:].replace("{", "{{").replace("}", "}}")
        # tqdm draws the bar to the terminal's width; the counts and the ETA are ours (tqdm's own
        # rate would not know the stage's units)
        layout = "{desc}: {percentage:3.0f}%|{bar}| " + info if f is not None else "{desc}: " + info
        if self._bar is None:
            self._bar = _bar_class()(total=100, initial=100.0 * (f or 0.0), file=self.bar_stream, leave=False,
                                     dynamic_ncols=True, bar_format=layout, desc=self.label)
        self._bar.bar_format = layout
        self._bar.n = 100.0 * (f or 0.0)
        self._bar.refresh()

    # ---- lifetime -------------------------------------------------------------------------------
    def beat(self, every: float = HEARTBEAT) -> None:
        """Look at the clock every ``every`` s in a thread of its own: a line falls due, and the bar
        moves, even while the running code reports nothing."""
        def loop() -> None:
            while not self._stop.wait(every):
                try:
                    self.tick()
                except Exception:          # noqa: BLE001 - progress must never fail a stage
                    return
        self._heart = threading.Thread(target=loop, name="progress-heartbeat", daemon=True)
        self._heart.start()

    def close(self) -> None:
        self._stop.set()
        if self._heart is not None and self._heart is not threading.current_thread():
            self._heart.join()
        with self._lock:
            self._closed = True
            if self._bar is not None:
                self._bar.close()              # leave=False: the bar goes, the stage's own line follows
                self._bar = None


@functools.cache
def _bar_class() -> Any:
    """tqdm's bar, imported when a bar is first drawn (not when the pipeline starts)."""
    from tqdm import tqdm

    class Bar(tqdm):
        monitor_interval = 0          # redrawn by the task itself: no tqdm monitor thread
    return Bar


@contextmanager
def _log_above_the_bar() -> Iterator[None]:
    """The console's log lines written through tqdm, which clears the bar, writes the line and draws
    the bar again below it. Only where a console handler exists (Hydra's): tqdm's redirect would
    otherwise add one."""
    root = logging.getLogger()
    if not any(type(h) is logging.StreamHandler and h.stream in (sys.stdout, sys.stderr) for h in root.handlers):
        yield
        return
    from tqdm.contrib.logging import logging_redirect_tqdm
    with logging_redirect_tqdm():
        yield


class Reporter:
    """Opens a Task per stage, in one mode for the whole job (``choose_mode``)."""

    def __init__(self, mode: str = "lines", *, clock: Callable[[], float] = time.monotonic,
                 emit: Callable[[str], None] | None = None, bar_stream: TextIO | None = None,
                 heartbeat: float | None = HEARTBEAT) -> None:
        if mode not in MODES:
            raise ValueError(f"progress mode {mode!r}: one of {MODES}")
        self.mode, self.clock, self.emit, self.bar_stream, self.heartbeat = mode, clock, emit, bar_stream, heartbeat

    @contextmanager
    def task(self, label: str, units: int | None = 1, unit: str = "chunk") -> Iterator[Task]:
        task = Task(label, units, unit, mode=self.mode, clock=self.clock, emit=self.emit,
                    bar_stream=self.bar_stream)
        with ExitStack() as stack:
            if self.mode == "bar":
                stack.enter_context(_log_above_the_bar())
            stack.enter_context(listening(task))
            stack.callback(task.close)
            if self.mode != "off" and self.heartbeat:
                task.beat(self.heartbeat)
            yield task
