"""Run ``python -m pipeline`` with a write that stalls at a chosen moment, so a test can SIGKILL it
there: ``python tests/interrupt_runner.py MODE MARKER <pipeline arguments>``.

Modes (the stall writes MARKER first, then sleeps until killed):

- ``parquet-half:<name>``: the first Parquet write whose target is named ``<name>`` (e.g. a cache
  key's file of the track stage: ``track``, or ``summary.parquet``) has written half its bytes;
- ``parquet-rename:<name>``: that write is complete and fsync'ed but not yet renamed;
- ``rrd``: half of the recording's bytes are in its temp file (the .rrd goes through the same
  atomic writer as the tables: ``parquet-half:recording.rrd``).

The patches replace library calls from outside the product code; nothing in ``pipeline/`` knows
about them.
"""

from __future__ import annotations

import io
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def stall(marker: str) -> None:
    Path(marker).write_text(str(os.getpid()))
    while True:
        time.sleep(1)


def matches(target: Path, name: str) -> bool:
    return name in (target.name, target.parent.name)


def install(mode: str, marker: str) -> None:
    import polars as pl

    from pipeline.storage import store

    if mode == "rrd":
        mode = "parquet-half:recording.rrd"
    kind, _, name = mode.partition(":")
    if kind in ("parquet-half", "parquet-rename"):
        original_write = store._atomic_write

        def atomic_write(path, write, binary=True, **options):
            if not (binary and matches(Path(path), name)):
                return original_write(path, write, binary, **options)

            def half_then_stall(f):
                buffer = io.BytesIO()
                write(buffer)
                data = buffer.getvalue()
                if kind == "parquet-half":
                    f.write(data[: len(data) // 2])
                    f.flush()
                    os.fsync(f.fileno())
                    stall(marker)
                f.write(data)

            if kind == "parquet-rename":
                real_replace = os.replace

                def replace_then_stall(src, dst):
                    if Path(dst) == Path(path):
                        stall(marker)
                    return real_replace(src, dst)
                store.os.replace = replace_then_stall
            return original_write(path, half_then_stall, binary, **options)

        store._atomic_write = atomic_write
        _ = pl
    else:
        raise SystemExit(f"unknown mode {mode!r}")


if __name__ == "__main__":
    mode, marker, *arguments = sys.argv[1:]
    sys.path.insert(0, str(ROOT))
    install(mode, marker)
    import runpy
    sys.argv = ["pipeline", *arguments]
    runpy.run_module("pipeline", run_name="__main__", alter_sys=True)      # as `python -m pipeline`
