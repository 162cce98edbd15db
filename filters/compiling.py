"""Telling a user that numba is compiling: the first job on a machine compiles the filters' kernels
(seconds to a minute per family, e.g. study 000's filter A stage took 21.5 s for 0.006 s of filtering),
later ones load them from numba's cache beside the source.

``compiling(what)`` wraps a kernel module's ``warm_up``: a load from the cache ends within
``NOTICE_AFTER_S``; a warm-up still running then is compiling, and says so once ("compiling the numba
kernels of filters.imm: once per install ..."), then how long it took. It logs (``logging``, logger
``filters.compiling``) and changes nothing that is computed. ``python -m pipeline.run.warmup``
compiles every kernel up front.
"""

from __future__ import annotations

import logging
import threading
import time
from contextlib import contextmanager
from typing import Iterator

log = logging.getLogger("filters.compiling")

NOTICE_AFTER_S = 1.0        # a cached kernel loads well within this (numba's own start ~0.8 s included)


@contextmanager
def compiling(what: str, notice_after_s: float = NOTICE_AFTER_S) -> Iterator[None]:
    """Around loading (or compiling) the kernels of ``what`` (a module name): one line when it is still
    running after ``notice_after_s`` seconds, and one with its duration when it ends."""
    said = threading.Event()

    def notice() -> None:
        said.set()
        log.info("compiling the numba kernels of %s: once per install (numba caches them); this job waits for it "
                 "(python -m pipeline.run.warmup compiles every kernel up front)", what)

    timer = threading.Timer(notice_after_s, notice)
    timer.daemon = True
    started = time.perf_counter()
    timer.start()
    try:
        yield
    finally:
        timer.cancel()
        if said.is_set():
            log.info("compiled the numba kernels of %s in %.1f s", what, time.perf_counter() - started)
