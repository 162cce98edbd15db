"""How far a long computation got, told to whoever listens, without knowing who that is.

A filter (or any long loop) takes ``progress = current()`` on the thread that called it, then says
``progress.start(total, unit, label)`` once it knows how much work there is and
``progress.advance(amount)`` as it goes, from any thread (a listener is thread-safe); a plain scan
loop wraps its range in ``counted``. With nobody listening (a notebook, a test, a filter used on
its own) ``current()`` is a no-op object. The pipeline listens while it runs a stage
(``listening(listener)``; pipeline.run.progress shows a bar or log lines). Nothing flows back: telling
progress never changes what is computed.

Its own module, not filters.base: a filter's code fingerprint (its stage cache key) covers the
modules it imports, so only the filters that report progress depend on this one.
"""

from __future__ import annotations

from contextlib import contextmanager
from contextvars import ContextVar
from typing import Iterator, Protocol


class Progress(Protocol):
    def start(self, total: float, unit: str = "step", label: str | None = None) -> None:
        """``total`` units of work follow (e.g. 360 scans), named ``unit``; ``label`` says whose (a
        filter's name). A second start begins a new piece of work."""

    def advance(self, amount: float = 1.0) -> None:
        """``amount`` more units done (fractions allowed: a chunk of the runs through one scan)."""


class _Silent:
    def start(self, total: float, unit: str = "step", label: str | None = None) -> None:
        pass

    def advance(self, amount: float = 1.0) -> None:
        pass


SILENT: Progress = _Silent()
_listener: ContextVar[Progress] = ContextVar("filters.progress.listener", default=SILENT)


def current() -> Progress:
    """Whoever listens in this context (SILENT if nobody). Threads a computation starts do not
    inherit it: take it before starting them and hand it over."""
    return _listener.get()


def counted(steps: range, unit: str = "scan", label: str | None = None) -> Iterator[int]:
    """``steps``, told to whoever listens: ``start(len(steps))`` first, then ``advance`` as the loop
    asks for the next step (the previous one's body has run), in at most about 1000 calls (a sonar
    run has 10 000 cheap scans). A filter's scan loop reads
    ``for k in counted(range(1, K), "scan", self.name):``. Nobody listening: the range itself."""
    progress = current()
    if progress is SILENT:
        yield from steps
        return
    progress.start(len(steps), unit, label)
    every, done = max(1, len(steps) // 1000), 0
    for step in steps:
        yield step
        done += 1
        if done == every:
            progress.advance(done)
            done = 0
    if done:
        progress.advance(done)


def counted_runs(runs: int, scans: int, label: str | None = None, per_call: int = 8,
                 unit: str = "scan") -> Iterator[tuple[int, int]]:
    """(first, stop) blocks of ``per_call`` runs, for a compiled loop that filters runs first..stop-1
    over all their ``scans`` in one call; whoever listens hears ``start(scans)`` first and, after
    each block, its share of the scans (``scans * (stop - first) / runs``). A filter reads
    ``for first, stop in counted_runs(R, K - 2, self.name): kernel(first, stop, ...)``."""
    progress = current()
    progress.start(scans, unit, label)
    for first in range(0, runs, per_call):
        stop = min(runs, first + per_call)
        yield first, stop
        progress.advance(scans * (stop - first) / runs)


@contextmanager
def listening(listener: Progress) -> Iterator[Progress]:
    """``listener`` hears what the code run inside the block reports."""
    token = _listener.set(listener)
    try:
        yield listener
    finally:
        _listener.reset(token)
